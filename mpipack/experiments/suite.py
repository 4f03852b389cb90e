"""``mpipack suite [--quick] [--out DIR]``: the stiff and extreme cases, each run as a real
``mpipack run`` under ``mpirun`` with a timeout, and a table of outcomes (DIR/suite.md, also
printed; DIR/suite.json has every figure).

Every case must either converge correctly (exit 0, certified, and the packing checked here
independently: overlaps recomputed from the dumped positions, and the analytic answer where
there is one) or be detected and reported (exit 3 with a message, exit 4 not certified within
its bound, or exit 2 for a start refused before it runs). A crash (exit 1 or a signal), a hang
(the timeout) or an exit 0 whose packing fails the independent check fails the case. Every
run is bounded by ``stop.max_iter`` and ``stop.max_seconds``.

The suite is a driver: it launches its own ``mpirun`` per case, so start it without mpirun.
The quick form (``--quick``, under about two minutes) is a representative subset and is a
test (tests/test_suite.py).
"""

import json
import math
import os
import subprocess
import sys
import time

from mpipack.errors import EXIT_FAILED, EXIT_INPUT, EXIT_OK
from mpipack.parallel.launcher import mpi_env

# the base of the parameter sweeps: N = 100 in 2D with the paper's Fig. 6 DAHA-S parameters,
# which certify in about 6500 iterations
SWEEP_BASE = ["n=100", "dim=2", "init.sigma=1.0", "method.form=\"S\"", "method.alpha=0.04",
              "method.beta=0.15", "method.gamma=0.07746", "method.c=2.0"]
# the paper's Fig. 6 DAHA-NS parameters (N = 100), for the starts that are not Gaussian
NS100 = ["method.form=\"NS\"", "method.alpha=0.07", "method.beta=0.5", "method.gamma=0.187", "method.c=2.0"]
# every case: the certified stop, no progress lines, no snapshot file
COMMON = ["stop.rule=\"certified\"", "output.progress_every=0", "output.snapshots=false"]


class Case:
    """One row of the table. ``allowed``: the outcomes that pass ("certified", "detected",
    "refused"); ``validate(result)`` returns a list of problems of an exit-0 packing (empty:
    right); ``prepare(case, folder)`` runs before (e.g. crafts a checkpoint)."""

    def __init__(self, name, expected, sets=(), scene=None, ranks=1, allowed=("certified", "detected"),
                 max_iter=20000, max_seconds=30.0, timeout=240, quick=False, validate=None,
                 prepare=None, extra=(), dump=True, rule_certified=True, same_as=None, note=None,
                 warmup=False, finding=None):
        self.name, self.expected, self.sets, self.scene, self.ranks = name, expected, list(sets), scene, ranks
        self.allowed, self.max_iter, self.max_seconds, self.timeout = set(allowed), max_iter, max_seconds, timeout
        self.quick, self.validate, self.prepare, self.extra, self.dump = quick, validate, prepare, list(extra), dump
        self.rule_certified, self.same_as, self.note, self.warmup = rule_certified, same_as, note, warmup
        self.finding = finding  # a known misbehaviour of the solver, reported (not patched here)


# ---- independent checks of a packing (from the dumped positions) ------------------------------
def pair_overlap(x, diam):
    """Max over pairs of (d_kl - r)/d_kl, 0 if none overlaps (numpy, in blocks; N up to ~2e4)."""
    import numpy as np
    n = x.shape[0]
    worst = 0.0
    for lo in range(0, n, 512):
        xi, di = x[lo:lo + 512], diam[lo:lo + 512]
        r = np.sqrt(((xi[:, None, :] - x[None, :, :]) ** 2).sum(-1))
        dkl = 0.5 * (di[:, None] + diam[None, :])
        rel = (dkl - r) / dkl
        idx = np.arange(lo, lo + xi.shape[0])
        rel[np.arange(xi.shape[0]), idx] = -np.inf  # not with itself
        worst = max(worst, float(rel.max()))
    return max(worst, 0.0)


def check_packing(res, overlap_tol=1.5e-3, w=None, w_rtol=2e-3, lam=None):
    """Problems of an exit-0 result: overlap recomputed from the dump, W (analytic if given)."""
    import numpy as np
    probs = []
    d = res.get("dump")
    if d is None:
        return ["no dump to check the packing with"]
    x, diam = d["x"], d["diam"]
    if not np.all(np.isfinite(x)):
        return ["non-finite positions"]
    ov = pair_overlap(x, diam)
    res["overlap_check"] = ov
    if ov > overlap_tol:
        probs.append(f"spheres overlap by {ov:.3g} d (recomputed from the positions)")
    if w is not None:
        xb = x.mean(axis=0)
        W = 0.5 * float(((x - xb) ** 2).sum())
        res["W_check"] = W
        if abs(W - w) > w_rtol * abs(w):
            probs.append(f"W = {W:.8g}, the optimum is {w:.8g}")
    if lam is not None:
        pl = d["pairs_lambda"]
        if pl.size != 1 or abs(float(pl[0]) - lam) > 1e-3 * lam:
            probs.append(f"multiplier {pl.tolist()}, expected {lam:g}")
    return probs


def two_spheres_answer(form):
    """Two spheres of diameter 1 in 1D: centres 1 apart, W = 1/4, lambda = 1/2 (NS) or 1/4 (S)."""
    return lambda res: check_packing(res, overlap_tol=1e-3, w=0.25, w_rtol=2e-3,
                                     lam=0.5 if form == "NS" else 0.25)


def chain_answer(n):
    """N spheres of diameter 1 in 1D: a contiguous chain, W = N (N^2 - 1) / 24."""
    return lambda res: check_packing(res, w=n * (n * n - 1) / 24.0, w_rtol=3e-3)


def plain_packing(res):
    return check_packing(res)


# ---- the one-point start: a checkpoint with every centre at the origin -------------------------
def one_point_checkpoint(folder, n, dim, form, log):
    """A checkpoint of N spheres all at the origin (no multiplier yet), made from a 1-iteration
    run's checkpoint: the exactly coincident start no scene can make (init.sigma >= 1e-6)."""
    seed_dir = os.path.join(folder, "seed")
    proc = run_cli(1, ["run", "--set", f"n={n}", "--set", f"dim={dim}", "--set", f"method.form=\"{form}\"",
                       "--set", "method.alpha=0.04", "--set", "method.beta=0.15", "--set", "stop.max_iter=1",
                       "--set", "stop.eps=0", "--set", "output.checkpoint_every=1", "--set", "output.snapshots=false",
                       "--quiet", "--out", seed_dir, "--overwrite"], folder, 120)
    log.append(proc)
    path = os.path.join(seed_dir, "checkpoint.h5")
    if proc.returncode != 0 or not os.path.exists(path):
        raise RuntimeError(f"could not make the seed checkpoint (exit {proc.returncode}): {proc.stderr[-500:]}")
    import json

    import h5py
    import numpy as np

    from mpipack.io import _h5
    with h5py.File(path, "r+") as f:
        for k in ("x", "x_prev"):
            f["particles"][k][...] = np.zeros((n, dim))
        for k in ("gid", "lambda"):
            dt = f["history"][k].dtype
            del f["history"][k]
            f["history"].create_dataset(k, shape=(0,), dtype=dt)
        f["history"]["offset"][...] = np.zeros(n + 1, dtype=f["history"]["offset"].dtype)
        # the file's checksums, of the arrays as they now are (serial: one share is the whole)
        sums = {f"{group}/{k}": str(_h5.checksum_rows(f[group][k][...], 0))
                for group in ("particles", "history") for k in f[group]}
        f.attrs["checksums"] = json.dumps(sums)
    return seed_dir


# ---- running -------------------------------------------------------------------------------------
def run_cli(ranks, args, cwd, timeout):
    cmd = ["mpirun", "--oversubscribe", "-n", str(ranks), sys.executable, "-m", "mpipack.cli"] + [str(a) for a in args]
    return subprocess.run(cmd, cwd=cwd, env=mpi_env(), capture_output=True, text=True, timeout=timeout)


def run_case(case, out_dir):
    """Run one case; returns the result dict (outcome, figures, pass/fail)."""
    import numpy as np
    folder = os.path.join(out_dir, case.name)
    os.makedirs(folder, exist_ok=True)
    run_dir = os.path.join(folder, "run")
    res = {"case": case.name, "expected": case.expected, "ranks": case.ranks}
    log = []
    args = ["run"] + ([case.scene] if case.scene else [])
    sets = list(case.sets) + (COMMON if case.rule_certified else
                              ["output.progress_every=0", "output.snapshots=false"])
    sets += [f"stop.max_iter={case.max_iter}", f"stop.max_seconds={case.max_seconds}"]
    t0 = time.perf_counter()
    try:
        if case.prepare is not None:
            args = ["run", "--restart", case.prepare(case, folder, log)]
            sets = [s for s in sets if s.split("=")[0].startswith(("stop.", "output.", "neighbor."))]
        for s in sets:
            args += ["--set", s]
        dump = os.path.join(folder, "final.npz")
        # the case's own scratch folder: its warm-up's (or an earlier suite's) run is replaced
        args += ["--out", run_dir, "--overwrite", "--quiet"] + (["--dump", dump] if case.dump else []) + case.extra
        if os.path.exists(dump):
            os.remove(dump)
        if case.warmup:  # the same command for one iteration first: kernels compiled and cached
            warm = [a if not str(a).startswith("stop.max_iter=") else "stop.max_iter=1" for a in args]
            run_cli(case.ranks, warm, folder, case.timeout)
        t0 = time.perf_counter()
        proc = run_cli(case.ranks, args, folder, case.timeout)
        res["seconds"] = time.perf_counter() - t0
        res["exit_code"] = proc.returncode
        res["stderr"] = proc.stderr.strip().splitlines()[-3:] if proc.stderr.strip() else []
    except subprocess.TimeoutExpired:
        res.update(seconds=time.perf_counter() - t0, exit_code=None, outcome="HANG", passed=False,
                   detail=f"no exit within {case.timeout} s (killed)")
        return res
    except RuntimeError as e:
        res.update(seconds=time.perf_counter() - t0, exit_code=None, outcome="CRASH", passed=False,
                   detail=f"set-up failed: {e}")
        return res
    summary = None
    path = os.path.join(run_dir, "summary.json")
    if os.path.exists(path):
        with open(path) as f:
            summary = json.load(f)
    res["summary"] = {k: summary.get(k) for k in ("iterations", "converged", "stop_reason", "max_overlap", "W",
                                                   "kkt_residual", "setup_seconds", "loop_seconds", "rebuilds",
                                                   "far_ghosts", "error", "exit_status", "certificate")} if summary else None
    res["dump"] = None
    if case.dump and os.path.exists(dump):
        with np.load(dump) as z:
            res["dump"] = {k: z[k] for k in z.files}
    rc = proc.returncode
    msg = next((line for line in reversed(res["stderr"]) if "error:" in line), None)
    if rc == 0:
        probs = []
        if summary is not None and not summary.get("converged"):
            probs.append(f"exit 0 without a certificate ({summary.get('stop_reason')})")
        validate = case.validate or plain_packing
        probs += validate(res)
        if probs:
            res.update(outcome="WRONG", detail="; ".join(probs))
        else:
            res.update(outcome="certified", detail="the packing checks out")
    elif rc == 3:
        res.update(outcome="detected", detail="exit 3: " + (msg or "numerical trouble"))
    elif rc == 4:
        it = summary.get("iterations") if summary else "?"
        reason = summary.get("stop_reason") if summary else "?"
        res.update(outcome="detected", detail=f"exit 4: not certified ({reason} after {it} iterations)")
    elif rc == 2:
        res.update(outcome="refused", detail="exit 2: " + (msg or "bad input"))
    else:
        res.update(outcome="CRASH", detail=f"exit {rc}: " + " | ".join(res["stderr"]))
    if case.same_as is not None:
        res["same_as"] = case.same_as
    res["passed"] = res["outcome"] in case.allowed
    if not res["passed"] and case.finding:
        res["finding"] = case.finding
    return res


def compare_dumps(a, b):
    """Bitwise equality of two dumps (positions, multipliers)."""
    import numpy as np
    if a is None or b is None:
        return False
    keys = ("gid", "x", "x_prev", "diam", "pairs_gid", "pairs_lambda")
    return all(k in a and k in b and a[k].shape == b[k].shape and np.array_equal(a[k], b[k]) for k in keys)


# ---- the cases ------------------------------------------------------------------------------------
def stability_edges():
    """Parameters just inside and just outside the stability region from ``mpipack check``'s
    analysis: two spheres DAHA-S (alpha = 0.35, gamma = sqrt(alpha beta), the exact scheme), and
    seven DAHA-S discs (alpha = 0.04, beta = 0.15, the cluster's scheme) in gamma."""
    from mpipack.analysis import check, stability
    from mpipack import config
    two = config.load("two-spheres", ["method.form=\"S\"", "method.alpha=0.35", "method.beta=1.4"])
    b_edge = check._edge(lambda b: stability.verdict(stability.with_param(two, "beta", b))[0], 1.4, 2.0, bisect=30)
    seven = config.load("paper-2d", ["n=7", "method.form=\"S\"", "method.alpha=0.04", "method.beta=0.15",
                                     "method.gamma=0.07"])
    g_edge = check._edge(lambda g: stability.verdict(stability.with_param(seven, "gamma", g))[0], 0.07, 0.5, bisect=30)
    return b_edge, g_edge


def cases(quick):
    b_edge, g_edge = stability_edges()
    two = ["method.form=\"S\"", "method.alpha=0.35"]
    out = [
        Case("N=1", "certified: nothing to do, W = 0", ["n=1", "dim=2"], quick=True, max_iter=500,
             allowed=("certified",),
             validate=lambda r: check_packing(r, w=0.0, w_rtol=0.0) if r["dump"] is not None else ["no dump"]),
        Case("N=2 1D NS (analytic)", "certified: r = d, W = d^2/4, lambda = d/2", [], scene="two-spheres",
             quick=True, validate=two_spheres_answer("NS")),
        Case("N=2 1D S (analytic)", "certified: r = d, W = d^2/4, lambda = 1/4",
             two + ["method.beta=1.4"], scene="two-spheres", validate=two_spheres_answer("S")),
        Case("one point S (exact)", "never a wrong packing: certified (symmetry broken) or detected",
             [], quick=True, max_iter=3000, prepare=lambda c, f, log: one_point_checkpoint(f, 50, 2, "S", log),
             note="the S gradient and the NS direction vanish at coincident centres: the run moves such "
                  "spheres apart by 1e-6 d in directions drawn from (seed, gid) before its first iteration "
                  "(init.separate), the same on any rank count; the cloud then expands (W 0 -> 173) and, "
                  "given 30000 iterations instead of this case's 3000, certifies (12450 iterations)"),
        Case("one point NS (exact)", "never a wrong packing: certified (symmetry broken) or detected",
             [], max_iter=3000, prepare=lambda c, f, log: one_point_checkpoint(f, 50, 2, "NS", log)),
        Case("one point S rule (4.3)", "the paper's rule: must not exit 0 with a one-point 'packing'",
             ["stop.rule=\"eps\"", "stop.eps=1e-6"], quick=True, rule_certified=False, max_iter=3000,
             prepare=lambda c, f, log: one_point_checkpoint(f, 50, 2, "S", log)),
        Case("near one point sigma=1e-6", "certified or detected", SWEEP_BASE + ["init.sigma=1e-6"],
             max_iter=20000),
        Case("beta=1e-3", "certified or detected", SWEEP_BASE + ["method.beta=1e-3"], max_iter=20000),
        Case("beta=1e9", "detected (divergence)", SWEEP_BASE + ["method.beta=1e9"], quick=True, max_iter=2000),
        Case("alpha=1e-8", "detected (no progress within the bound)", SWEEP_BASE + ["method.alpha=1e-8"],
             quick=True, max_iter=2000),
        Case("alpha=1", "certified or detected", SWEEP_BASE + ["method.alpha=1.0"], max_iter=20000),
        Case("c=1e-3", "certified or detected", SWEEP_BASE + ["method.c=1e-3"], max_iter=20000),
        Case("c=100", "certified or detected", SWEEP_BASE + ["method.c=100.0"], max_iter=20000),
        Case("gamma=0 N=2", "detected: a centre (|z| = 1), the contact oscillates forever",
             two + ["method.beta=1.4", "method.gamma=0.0"], scene="two-spheres", quick=True, max_iter=5000),
        Case("gamma=0 N=100", "detected", SWEEP_BASE + ["method.gamma=0.0"], max_iter=20000),
        Case(f"N=2 S inside (beta={0.97 * b_edge:.4g})", "certified (check: stable)",
             two + [f"method.beta={0.97 * b_edge!r}"], scene="two-spheres", quick=True,
             validate=two_spheres_answer("S")),
        Case(f"N=2 S outside (beta={1.03 * b_edge:.4g})", "detected (check: not stable)",
             two + [f"method.beta={1.03 * b_edge!r}"], scene="two-spheres", allowed=("detected",), quick=True,
             max_iter=5000),
        Case(f"N=7 S inside (gamma={1.1 * g_edge:.4g})", "certified (check: stable)",
             ["n=7", "dim=2", "init.sigma=1.0", "method.form=\"S\"", "method.alpha=0.04", "method.beta=0.15",
              f"method.gamma={1.1 * g_edge!r}"], max_iter=60000, max_seconds=60),
        Case(f"N=7 S outside (gamma={0.9 * g_edge:.4g})", "detected (check: not stable)",
             ["n=7", "dim=2", "init.sigma=1.0", "method.form=\"S\"", "method.alpha=0.04", "method.beta=0.15",
              f"method.gamma={0.9 * g_edge!r}"], allowed=("detected",), max_iter=60000, max_seconds=60),
        Case("spread start no contacts", "certified (falls together)",
             ["n=200", "dim=2", "init.sigma=200.0"], allowed=("certified",), max_iter=60000, max_seconds=60),
        Case("spread start, fixed parameters", "certified or detected (it collapses and bounces back "
             "with a period of ~6000 iterations)", SWEEP_BASE + ["n=200", "init.sigma=200.0"], max_iter=40000,
             max_seconds=60),
        Case("dense start 2D N=2e4 sigma=1", "detected within its bound, or refused for memory",
             ["n=20000", "dim=2", "init.sigma=1.0", "method.alpha=0.0078", "method.beta=2800.0", "method.gamma=0.016"], allowed=("detected", "refused", "certified"), max_iter=3000,
             max_seconds=60, timeout=900, dump=False),
        Case("lattice spacing 0.5", "certified or detected",
             ["n=300", "dim=2", "init.kind=\"lattice\"", "init.spacing=0.5"] + NS100, quick=True, max_iter=10000),
        Case("1D chain N=20 NS", "certified: W = N(N^2-1)/24",
             ["n=20", "dim=1", "init.sigma=2.0", "method.form=\"NS\"", "method.alpha=0.1", "method.beta=0.5",
              "method.gamma=0.05"], quick=True, validate=chain_answer(20), max_iter=40000),
        Case("1D chain N=200 NS (paper N=7 parameters)", "detected (check: not stable)",
             ["n=200", "dim=1", "init.sigma=20.0", "method.form=\"NS\"", "method.alpha=0.3", "method.beta=3.0",
              "method.gamma=0.9487"],
             validate=chain_answer(200), max_iter=20000),
        Case("3D N=500", "certified or detected",
             ["n=500", "dim=3", "init.sigma=0.63", "method.alpha=0.028", "method.beta=220.0",
              "method.gamma=0.06"], max_iter=20000, max_seconds=60),
        Case("diameters 1:10 N=500", "certified or detected",
             ["n=500", "dim=2", "particles.diameter_max=10.0", "init.kind=\"ball\"", "init.fraction=0.3"] + NS100,
             max_iter=20000),
        Case("diameters 1:100 N=500", "bounded; set-up and rebuilds linear in N (with N=4000)",
             ["n=500", "dim=2", "particles.diameter_max=100.0", "init.kind=\"ball\"", "init.fraction=0.3"] + NS100,
             quick=True, max_iter=200, dump=False, warmup=True),
        Case("diameters 1:100 N=4000", "bounded; set-up and rebuilds linear in N (with N=500)",
             ["n=4000", "dim=2", "particles.diameter_max=100.0", "init.kind=\"ball\"", "init.fraction=0.3"] + NS100,
             quick=True, max_iter=200, dump=False, warmup=True),
        Case("N=2 on 3 ranks (empty rank)", "certified, bitwise as on 1 rank", [], scene="two-spheres", ranks=3,
             quick=True, validate=two_spheres_answer("NS"), same_as="N=2 1D NS (analytic)"),
        Case("jumps across ranks 1 rank", "reference for the 3-rank run",
             ["n=300", "dim=2", "init.sigma=0.3", "method.form=\"NS\"", "method.alpha=0.3", "method.beta=3.0",
              "method.gamma=0.9487", "output.metrics_every=1"], quick=True, max_iter=300),
        Case("jumps across ranks 3 ranks", "bitwise as on 1 rank",
             ["n=300", "dim=2", "init.sigma=0.3", "method.form=\"NS\"", "method.alpha=0.3", "method.beta=3.0",
              "method.gamma=0.9487", "output.metrics_every=1"], ranks=3, quick=True, max_iter=300,
             same_as="jumps across ranks 1 rank"),
    ]
    if quick:
        out = [c for c in out if c.quick]
    return out


# ---- the table ---------------------------------------------------------------------------------
def _num(v, fmt="{:.3g}"):
    if v is None:
        return "-"
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return fmt.format(v)


def table(results):
    head = ("| case | expected | outcome | iterations | max overlap | W | exit code | seconds |\n"
            "|---|---|---|---|---|---|---|---|")
    rows = [head]
    for r in results:
        s = r.get("summary") or {}
        mark = "✓" if r["passed"] else ("✗ FINDING" if r.get("finding") else "✗ FAIL")
        outcome = f"{r['outcome']} {mark}: {r.get('detail', '')}".replace("|", "/")
        rows.append(f"| {r['case']} | {r['expected']} | {outcome} | {_num(s.get('iterations'), '{}')} | "
                    f"{_num(s.get('max_overlap'))} | {_num(s.get('W'), '{:.6g}')} | "
                    f"{'-' if r.get('exit_code') is None else r['exit_code']} | {r.get('seconds', 0):.1f} |")
    return "\n".join(rows)


def notes(results):
    """Cross-case figures: set-up scaling of the 1:100 diameters, bitwise equality, jumps."""
    by = {r["case"]: r for r in results}
    out = []
    a, b = by.get("diameters 1:100 N=500"), by.get("diameters 1:100 N=4000")
    if a and b and a.get("summary") and b.get("summary"):
        ta, tb = a["summary"]["setup_seconds"], b["summary"]["setup_seconds"]
        la, lb = a["summary"]["loop_seconds"], b["summary"]["loop_seconds"]
        ok = tb / max(ta, 1e-9) < 20 and lb / max(la, 1e-9) < 20
        ra, rb = a["summary"].get("rebuilds") or 1, b["summary"].get("rebuilds") or 1
        out.append(f"- diameters 1:100 (cells sized for the largest sphere): set-up (the start's pair search and "
                   f"the kernels' load) {ta:.3f} s at N = 500, {tb:.3f} s at N = 4000 (x{tb / max(ta, 1e-9):.1f} "
                   f"for x8 spheres; quadratic would be x64); {a['summary'].get('iterations')} iterations with "
                   f"{ra} and {rb} rebuilds: {la:.3f} s -> {lb:.3f} s (x{lb / max(la, 1e-9):.1f}) "
                   f"{'✓' if ok else '✗ FAIL'}")
        b["passed"] = b["passed"] and ok
    for r in results:
        if r.get("same_as"):
            ref = by.get(r["same_as"])
            same = ref is not None and compare_dumps(ref.get("dump"), r.get("dump"))
            r["passed"] = r["passed"] and same
            out.append(f"- {r['case']}: positions and multipliers {'bitwise equal to' if same else 'DIFFER from'} "
                       f"'{r['same_as']}' {'✓' if same else '✗ FAIL'}")
    j = by.get("jumps across ranks 3 ranks")
    if j:
        path = os.path.join(j["folder"], "run", "metrics.csv") if j.get("folder") else None
        if path and os.path.exists(path):
            with open(path) as f:
                rows = [line.split(",") for line in f.read().splitlines()[1:]]
            if rows:
                w = [float(row[5]) for row in rows]
                rg = [math.sqrt(2 * v / 300) for v in w]
                k = max(range(len(rg)), key=lambda i: rg[i])
                s = j.get("summary") or {}
                out.append(f"- jumps across ranks: radius of gyration {rg[0]:.3g} after iteration 1, {rg[k]:.3g} "
                           f"at its largest (iteration {k + 1}); the 3 ranks' regions are about the cloud's "
                           f"size / 3, so spheres crossed several in one iteration; rebuilds {s.get('rebuilds')}, "
                           f"far ghosts {s.get('far_ghosts')}")
    return out


def main(args):
    """``mpipack suite``: returns 0 when every case passes, 1 otherwise."""
    from mpipack.parallel.launcher import world_size
    if world_size() > 1:
        print("mpipack: error: start mpipack suite without mpirun: it launches its own", file=sys.stderr)
        return EXIT_INPUT
    out = args.out or os.path.join("mpipack-out", "suite-quick" if args.quick else "suite")
    os.makedirs(out, exist_ok=True)
    todo = cases(args.quick)
    if args.cases:
        want = [w.strip() for w in args.cases.split(",")]
        todo = [c for c in todo if any(c.name == w or c.name.startswith(w) for w in want)]
        if not todo:
            print(f"mpipack: error: --cases: none of {want} is a case of this suite", file=sys.stderr)
            return EXIT_INPUT
    results = []
    t_all = time.perf_counter()
    for c in todo:
        r = run_case(c, out)
        r["folder"] = os.path.join(out, c.name)
        results.append(r)
        print(f"  {c.name:<45s} {r['outcome']:<10s} exit {r.get('exit_code')} {r.get('seconds', 0):6.1f} s "
              f"{'ok' if r['passed'] else 'FAIL'}", flush=True)
    extra = notes(results)
    passed = sum(r["passed"] for r in results)
    extra += [f"- finding ({r['case']}): {r['finding']}" for r in results if r.get("finding")]
    extra += [f"- note ({c.name}): {c.note}" for c in todo if c.note]
    text = (f"# mpipack suite{' (quick)' if args.quick else ''}\n\n"
            f"{passed} of {len(results)} cases pass ({time.perf_counter() - t_all:.0f} s on this machine). "
            "A case passes when it converges correctly (exit 0, certified, the packing rechecked from the "
            "positions and against the analytic answer where there is one) or is detected (exit 3 with a "
            "message, or 4: not certified within its bound) or refused (exit 2) as its 'expected' column "
            "allows; a crash, a hang or an exit 0 with a wrong packing fails.\n\n"
            + table(results) + "\n\n" + "\n".join(extra) + "\n")
    with open(os.path.join(out, "suite.md"), "w") as f:
        f.write(text)
    with open(os.path.join(out, "suite.json"), "w") as f:
        json.dump([{k: v for k, v in r.items() if k != "dump"} for r in results], f, indent=1, default=str)
    print()
    print(text, flush=True)
    return EXIT_OK if passed == len(results) else EXIT_FAILED
