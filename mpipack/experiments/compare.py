"""``mpipack compare SCENE``: error against run time. Runs a set of methods over a ladder of
tolerances and seeds and draws work-precision diagrams: each error measure (max overlap, KKT
residual, |W - W_ref| / W_ref, the paper's A) against wall time and against iterations, one
curve per method (median over seeds, band from min to max), with the tolerance ladder's stops
as markers on the curves; PNG, CSV and a markdown table in --out.

Runs. Every run is an ordinary ``mpipack run`` (``runner.run_request``, in this process, one rank)
with the paper's stop rule (4.3) at the tolerance (NAP/NAV: eps_inner = eps / 1000, as the
paper's Table 1), bounded by stop.max_iter. Per method and seed:

* one run per tolerance, without metrics: its stop (iterations, loop seconds) and its final
  figures (summary.json) are the ladder's points;
* one more run at the tightest tolerance with ``output.metrics_every`` = iterations / 100: its
  metrics.csv is the curve. The trajectory does not depend on the tolerance (the stop rule
  only ends it), so the looser runs are prefixes of it; its time axis is rescaled by the
  tightest run's loop seconds over its own, which removes the metrics passes' cost.

Work (the "iterations" axis) is kernel passes: iterations for DAHA/AHA, inner iterations for
NAP/NAV (the paper's T), the outer count of metrics.csv scaled by the run's mean inner steps
per outer step. W_ref is the scene's output.w_optimum, else 3 for 7 unit discs in 2D (the
paper's optimum), else the smallest final W of a certified run of the same seed (the same
start) over all methods: "W minus its best value".

Methods (default): the paper's DAHA-S, DAHA-NS, NAP-NS, NAP-S and NAV-NS with the paper's
parameters for N = 7 (Table 1) and N = 100 (Fig. 6), for other N the set of the nearer of the
two (labelled so); for N >= 1000 DAHA-S only (sections 4.3/4.4 give no other method there),
plus the scene's own method and parameters ("scene"). ``--methods`` takes names
(DAHA-S, DAHA-NS, AHA-S, AHA-NS, NAP-S, NAP-NS, NAV-S, NAV-NS, scene) with optional
parameters: ``DAHA-S:alpha=0.04:beta=0.15:gamma=0.08``.

A peer code's curve (``--peer [LABEL=]FILE``, repeatable, one file per seed): either a CSV with
the columns of PEER_COLUMNS (label, seed, n, wall_seconds, work, max_overlap, A, W, kkt_residual;
missing ones left empty) or the JSON of ``tools/peers/lammps_fire.py --keep-checks --json``
(its checks: step, seconds, max_overlap, W/N^2). To put LAMMPS FIRE beside mpipack:

    mpipack run SCENE --seed S --set stop.max_iter=0 --set stop.eps=0 --dump start-S.npz
    . tools/peers/lammps_env.sh
    $LAMMPS_PYTHON tools/peers/lammps_fire.py start-S.npz --keep-checks --json fire-S.json
    mpipack compare SCENE --seeds S --peer FIRE=fire-S.json

(the start is the scene's own, made by mpipack; FIRE's steps are its "work"; its checks give
max overlap and W, which tools/peers/score.py computes from positions exactly as here; the
KKT residual and A need multipliers or overlap areas and stay empty). Any other code: write
the CSV, e.g. by scoring saved positions with tools/peers/score.py.
"""

import csv
import json
import math
import os
import sys
import time

MEASURES = (("max_overlap", "max overlap (d_kl - r)/d_kl"), ("kkt_residual", "KKT residual"),
            ("W_err", "|W - W_ref| / W_ref"), ("A", "mean overlap proportion A"))
PEER_COLUMNS = ("label", "seed", "n", "wall_seconds", "work", "max_overlap", "A", "W", "kkt_residual")
FLOOR = 1e-17  # zeros on a log axis
PAPER_METHODS = ("DAHA-S", "DAHA-NS", "NAP-NS", "NAP-S", "NAV-NS")
# the paper's parameters at N = 2000 (sections 4.3 and 4.4), DAHA-S only
PAPER_2000 = {2: dict(name="daha", form="S", alpha=7.8e-3, beta=2.8e3, gamma=1.6e-2, c=2.0),
              3: dict(name="daha", form="S", alpha=2.8e-2, beta=2.2e2, gamma=5.6e-2, c=2.0)}


class CompareError(ValueError):
    pass


# ---- methods, tolerances, seeds -------------------------------------------------------------------
def _paper_sets():
    from .paper import F6_PARAMS, T1_PARAMS
    return {7: T1_PARAMS, 100: F6_PARAMS}


def default_methods(scene):
    """[(label, method overrides)] for a scene (see the module docstring)."""
    out = []
    n, b = scene.n, scene.dim
    if n >= 1000:
        if b in PAPER_2000:
            out.append(("DAHA-S (paper N=2000)", dict(PAPER_2000[b])))
    else:
        sets = _paper_sets()
        near = min(sets, key=lambda k: abs(math.log(n / k)))
        for name in PAPER_METHODS:
            p = dict(sets[near][name])
            if p["name"] in ("daha", "aha") and "gamma" not in p:
                p["gamma"] = math.sqrt(p["alpha"] * p["beta"])
            out.append((name + ("" if near == n else f" (paper N={near})"), p))
    m = scene.method
    own = dict(name=m.name, form=m.form, alpha=m.alpha, beta=m.beta, gamma=m.gamma, c=m.c,
               l_inner=m.l_inner, tau=m.tau)
    if not any(all(own.get(k) == v for k, v in p.items()) for _, p in out):
        out.append((f"scene {m.name.upper()}-{m.form}", own))
    return out


def parse_methods(text, scene):
    if not text:
        return default_methods(scene)
    out = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        name, *params = item.split(":")
        key = name.strip()
        if key.lower() == "scene":
            m = scene.method
            p = dict(name=m.name, form=m.form, alpha=m.alpha, beta=m.beta, gamma=m.gamma, c=m.c,
                     l_inner=m.l_inner, tau=m.tau)
        else:
            try:
                meth, form = key.split("-")
            except ValueError:
                raise CompareError(f"--methods: {key!r} is not METHOD-FORM (e.g. DAHA-S) or 'scene'") from None
            if meth.lower() not in ("daha", "aha", "nap", "nav") or form.upper() not in ("S", "NS"):
                raise CompareError(f"--methods: unknown method {key!r}")
            sets = _paper_sets()
            near = min(sets, key=lambda k: abs(math.log(scene.n / k)))
            base = sets[near].get(f"{meth.upper()}-{form.upper()}")
            p = dict(base) if base else dict(name=meth.lower(), form=form.upper(), alpha=scene.method.alpha,
                                             beta=scene.method.beta)
            p["name"], p["form"] = meth.lower(), form.upper()
        for kv in params:
            if "=" not in kv:
                raise CompareError(f"--methods: {kv!r} in {item!r} is not key=value")
            k, v = kv.split("=", 1)
            try:
                p[k.strip()] = float(v)
            except ValueError:
                raise CompareError(f"--methods: {kv!r} in {item!r}: not a number") from None
        if p["name"] in ("daha", "aha") and "gamma" not in p:
            p["gamma"] = math.sqrt(p["alpha"] * p["beta"])
        out.append((item if params else key, p))
    if not out:
        raise CompareError("--methods: no method given")
    return out


def parse_floats(text, what):
    try:
        v = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise CompareError(f"{what}: not a list of numbers: {text!r}") from None
    if not v or any(not (x > 0 and math.isfinite(x)) for x in v):
        raise CompareError(f"{what}: positive numbers expected, got {text!r}")
    return v


def parse_seeds(text, default):
    if not text:
        return list(default)
    parts = [t.strip() for t in text.split(",") if t.strip()]
    try:
        vals = [int(t) for t in parts]
    except ValueError:
        raise CompareError(f"--seeds: whole numbers expected, got {text!r}") from None
    if any(v < 0 for v in vals):
        raise CompareError(f"--seeds: seeds are >= 0, got {text!r}")
    if len(vals) == 1 and "," not in text:
        if vals[0] < 1:
            raise CompareError("--seeds: a count must be >= 1")
        return list(range(1, vals[0] + 1))
    return vals


# ---- one run --------------------------------------------------------------------------------------
def method_sets(p, eps):
    sets = []
    for k, v in p.items():
        if k in ("name", "form"):
            sets.append(f'method.{k}="{v}"')
        elif k in ("l_inner",):
            sets.append(f"method.{k}={int(v)}")
        else:
            sets.append(f"method.{k}={float(v)!r}")
    if p["name"] in ("nap", "nav"):
        sets.append(f"method.eps_inner={eps * 1e-3!r}")
    return sets


def run_one(scene_src, base_sets, p, eps, seed, out, max_iter, metrics_every=0):
    """One run in this process (the engine's ``run_request``, as ``mpipack run`` does); returns
    (exit code, summary dict, metrics rows)."""
    from mpipack.engine import runner
    from mpipack.parallel.comm import Comm
    sets = list(base_sets) + method_sets(p, eps) + [
        'stop.rule="eps"', f"stop.eps={eps!r}", f"stop.max_iter={max_iter}", "output.progress_every=0",
        "output.snapshots=false", f"output.metrics_every={metrics_every}"]
    request = runner.RunRequest(scene=scene_src or None, overrides=tuple(sets), seed=seed, out=out, quiet=True,
                                overwrite=True)  # compare's own run folders: a warm-up's or an earlier compare's
    err = sys.stderr
    sys.stderr = open(os.devnull, "w")  # a run that fails says so in its summary
    try:
        outcome = runner.run_request(Comm(), request)
    finally:
        sys.stderr.close()
        sys.stderr = err
    code, summary = outcome.code, outcome.summary or {}
    rows = []
    mpath = os.path.join(out, "metrics.csv")
    if metrics_every > 0 and os.path.exists(mpath):
        with open(mpath) as f:
            rows = [{k: float(v) if v not in ("", "nan") else math.nan for k, v in r.items()}
                    for r in csv.DictReader(f)]
    return code, summary, rows


# ---- peers ---------------------------------------------------------------------------------------
MAX_PEER_BYTES = 64 * 1024 * 1024  # a peer's curve is a few KiB


def read_peer(spec):
    """[(label, seed, n, rows)] from a --peer argument."""
    label, path = (spec.split("=", 1) if "=" in spec and not os.path.exists(spec) else (None, spec))
    if not os.path.isfile(path):
        raise CompareError(f"--peer: no such file: {path}")
    if os.path.getsize(path) > MAX_PEER_BYTES:
        raise CompareError(f"--peer: {path}: {os.path.getsize(path)} bytes, more than a peer's curve")
    try:
        with open(path, encoding="utf-8") as f:
            text = f.read()
    except UnicodeDecodeError:
        raise CompareError(f"--peer: {path}: not a text file (a CSV in compare's format or a "
                           f"lammps_fire.py --keep-checks JSON)") from None
    if path.endswith(".json"):
        try:
            d = json.loads(text)
        except ValueError as e:
            raise CompareError(f"--peer: {path}: not JSON ({e})") from None
        n = int(d.get("n") or 0)
        checks = d.get("checks")
        if not checks:
            raise CompareError(f"--peer: {path}: no 'checks' (run lammps_fire.py with --keep-checks)")
        rows = [{"wall_seconds": c["seconds"], "work": c["step"], "max_overlap": c["max_overlap"],
                 "W": c["W_over_N2"] * n * n if n else math.nan, "A": math.nan, "kkt_residual": math.nan}
                for c in checks]
        return [(label or "LAMMPS FIRE", int(d.get("seed", 0) or 0), n or None, rows)]
    out = {}
    reader = csv.DictReader(text.splitlines())
    missing = [k for k in ("wall_seconds", "work", "max_overlap") if k not in (reader.fieldnames or [])]
    if missing:
        raise CompareError(f"--peer: {path}: not a curve in compare's format (no column "
                           f"{', '.join(missing)}; columns: {', '.join(PEER_COLUMNS)})")
    for r in reader:
        lab = label or r.get("label") or os.path.splitext(os.path.basename(path))[0]
        seed = int(float(r.get("seed") or 0))
        n = int(float(r["n"])) if r.get("n") else None
        try:
            row = {k: (float(r[k]) if r.get(k) not in (None, "") else math.nan)
                   for k in ("wall_seconds", "work", "max_overlap", "A", "W", "kkt_residual")}
        except ValueError as e:
            raise CompareError(f"--peer: {path}: line {reader.line_num}: {e}") from None
        out.setdefault((lab, seed, n), []).append(row)
    if not out:
        raise CompareError(f"--peer: {path}: no rows (columns: {', '.join(PEER_COLUMNS)})")
    return [(lab, seed, n, rows) for (lab, seed, n), rows in out.items()]


# ---- the experiment ------------------------------------------------------------------------------
def w_reference(scene, finals):
    """{seed: W_ref} (see the module docstring) and a word on where it came from."""
    if scene.output.w_optimum is not None:
        return {s: scene.output.w_optimum for s in finals}, "the scene's output.w_optimum"
    p = scene.particles
    if scene.n == 7 and scene.dim == 2 and p.diameter == 1.0 and p.d_max == 1.0:
        return {s: 3.0 for s in finals}, "the optimum of 7 unit discs, W = 3"
    ref = {}
    for s, runs in finals.items():
        ok = [r["W"] for r in runs if r.get("converged") and r.get("W") is not None]
        if not ok:
            ok = [r["W"] for r in runs if (r.get("max_overlap") or 1) <= 1e-3 and r.get("W") is not None]
        ref[s] = min(ok) if ok else math.nan
    return ref, "the smallest W of a certified run from the same start (seed)"


def compare_scene(scene_src, base_sets, methods, tols, seeds, out, max_iter, log):
    """Run everything for one scene; returns a dict of runs and curves."""
    from .. import config
    scene = config.load(scene_src, base_sets)
    tols = sorted(tols, reverse=True)
    tight = tols[-1]
    runs = []  # ladder points
    curves = []  # trajectories
    for label, p in methods:
        # a short run first: the method's kernels are compiled (or loaded) outside the timed runs
        run_one(scene_src, base_sets, p, tight, seeds[0], os.path.join(out, "runs", "warmup"), 3, metrics_every=1)
        for seed in seeds:
            stop = {}
            for eps in tols:
                d = os.path.join(out, "runs", _slug(label), f"seed{seed}", f"eps{eps:g}")
                code, summ, _ = run_one(scene_src, base_sets, p, eps, seed, d, max_iter)
                work = _work(summ)
                r = {"method": label, "seed": seed, "eps": eps, "exit_code": code,
                     "iterations": summ.get("iterations"), "work": work,
                     "seconds": summ.get("loop_seconds"), "converged": summ.get("converged"),
                     "stop_reason": summ.get("stop_reason"), "max_overlap": summ.get("max_overlap"),
                     "kkt_residual": summ.get("kkt_residual"), "W": summ.get("W"), "A": summ.get("overlap_A"),
                     "error": summ.get("error")}
                runs.append(r)
                stop[eps] = r
            ref = stop[tight]
            k = max(1, int((ref["iterations"] or 1) // 100))
            d = os.path.join(out, "runs", _slug(label), f"seed{seed}", "curve")
            code, summ, rows = run_one(scene_src, base_sets, p, tight, seed, d, max_iter, metrics_every=k)
            scale = (ref["seconds"] / summ["loop_seconds"]) if ref["seconds"] and summ.get("loop_seconds") else 1.0
            per = _work(summ) / summ["iterations"] if summ.get("iterations") else 1.0
            pts = [{"work": r["iteration"] * per, "seconds": r["wall_seconds"] * scale,
                    "max_overlap": r["max_overlap"], "kkt_residual": r["kkt_residual"], "W": r["W"], "A": r["A"]}
                   for r in rows]
            curves.append({"method": label, "seed": seed, "points": pts, "metrics_every": k})
            log(f"  {label:<28s} seed {seed}: " + ", ".join(
                f"eps {e:g}: {stop[e]['iterations']} it {stop[e]['seconds'] or 0:.3f} s"
                + ("" if stop[e]["exit_code"] in (0, 4) else f" (exit {stop[e]['exit_code']})") for e in tols))
    finals = {}
    for r in runs:
        finals.setdefault(r["seed"], []).append(r)
    wref, wsrc = w_reference(scene, finals)
    for r in runs:
        r["W_err"] = _werr(r.get("W"), wref.get(r["seed"]))
    for c in curves:
        for pnt in c["points"]:
            pnt["W_err"] = _werr(pnt.get("W"), wref.get(c["seed"]))
    return {"scene": scene, "label": f"{scene.name}, N = {scene.n}, {scene.dim}D", "runs": runs, "curves": curves,
            "tols": tols, "wref": wref, "wsrc": wsrc, "peers": []}


def _werr(w, ref):
    if w is None or ref is None or not (isinstance(w, float) or isinstance(w, int)) or not math.isfinite(ref) \
            or not math.isfinite(w) or ref == 0:
        return math.nan
    return abs(w - ref) / abs(ref)


def _work(summ):
    it = summ.get("iterations") or 0
    inner = summ.get("inner_iterations") or 0
    return float(inner if inner > 0 else it)


def _slug(label):
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in label)


# ---- aggregation ---------------------------------------------------------------------------------
def band(curves, xkey, ykey, grid):
    """(median, lo, hi) of y over the curves at each x of grid. A curve contributes from its
    first point on; after its last point it holds its last value (what the run returned)."""
    import numpy as np
    cols = []
    for pts in curves:
        xs = np.array([p[xkey] for p in pts], float)
        ys = np.array([p[ykey] for p in pts], float)
        ok = np.isfinite(xs) & np.isfinite(ys)
        xs, ys = xs[ok], ys[ok]
        if xs.size == 0:
            continue
        ys = np.maximum(ys, FLOOR)
        col = np.full(grid.shape, np.nan)
        inside = grid >= xs[0]
        idx = np.searchsorted(xs, grid[inside], side="right") - 1
        col[inside] = ys[np.clip(idx, 0, len(ys) - 1)]
        cols.append(col)
    if not cols:
        return None
    a = np.vstack(cols)
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmedian(a, axis=0), np.nanmin(a, axis=0), np.nanmax(a, axis=0)


def _median(v):
    v = sorted(x for x in v if x is not None and isinstance(x, (int, float)) and math.isfinite(x))
    if not v:
        return math.nan
    k = len(v)
    return v[k // 2] if k % 2 else 0.5 * (v[k // 2 - 1] + v[k // 2])


def table_rows(res):
    """One row per method and tolerance: medians over seeds."""
    rows = []
    methods = []
    for r in res["runs"]:
        if r["method"] not in methods:
            methods.append(r["method"])
    for m in methods:
        for eps in res["tols"]:
            rs = [r for r in res["runs"] if r["method"] == m and r["eps"] == eps]
            rows.append({"method": m, "eps": eps, "seeds": len(rs),
                         "work": _median([r["work"] for r in rs]), "seconds": _median([r["seconds"] for r in rs]),
                         "max_overlap": _median([r["max_overlap"] for r in rs]),
                         "kkt_residual": _median([r["kkt_residual"] for r in rs]),
                         "W_err": _median([r["W_err"] for r in rs]), "A": _median([r["A"] for r in rs]),
                         "fired": sum(r["stop_reason"] == "eps" for r in rs),
                         "certified": sum(bool(r["converged"]) for r in rs),
                         "failed": sum(r["exit_code"] not in (0, 4) for r in rs)})
    return rows


def _g(v, fmt="{:.2g}"):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)


def markdown(results, tols_text, seeds, elapsed, pngs):
    L = ["# mpipack compare: error against run time", "",
         f"Seeds {', '.join(map(str, seeds))}; tolerances (4.3) {tols_text}; {elapsed:.0f} s in all. "
         "Each row: medians over the seeds of the run stopped by (4.3) at that tolerance (work = kernel "
         "passes: iterations, or inner iterations for NAP/NAV; seconds = loop time of the run). "
         "'(4.3)' counts the runs it stopped, 'certified' those whose final state meets the certificate "
         "(max overlap <= 1e-3, KKT <= 1e-2, W settled), 'failed' those that ended in numerical trouble.", ""]
    for res, png in zip(results, pngs):
        L += [f"## {res['label']}", "", f"W_ref: {res['wsrc']}.", "", f"![work-precision]({os.path.basename(png)})", "",
              "| method | eps | work | seconds | max overlap | KKT | W err | A | (4.3) | certified | failed |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in table_rows(res):
            L.append(f"| {r['method']} | {r['eps']:g} | {_g(r['work'], '{:.0f}')} | {_g(r['seconds'], '{:.3g}')} | "
                     f"{_g(r['max_overlap'])} | {_g(r['kkt_residual'])} | {_g(r['W_err'])} | {_g(r['A'])} | "
                     f"{r['fired']}/{r['seeds']} | {r['certified']}/{r['seeds']} | {r['failed']} |")
        L.append("")
    return "\n".join(L)


def write_csv(results, out):
    with open(os.path.join(out, "ladder.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene", "n", "method", "seed", "eps", "exit_code", "stop_reason", "converged", "iterations",
                    "work", "seconds", "max_overlap", "kkt_residual", "W", "W_err", "A"])
        for res in results:
            for r in res["runs"]:
                w.writerow([res["scene"].name, res["scene"].n, r["method"], r["seed"], r["eps"], r["exit_code"],
                            r["stop_reason"], r["converged"], r["iterations"], r["work"], r["seconds"],
                            r["max_overlap"], r["kkt_residual"], r["W"], r["W_err"], r["A"]])
    with open(os.path.join(out, "curves.csv"), "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scene", "n", "method", "seed", "work", "seconds", "max_overlap", "kkt_residual", "W", "W_err", "A"])
        for res in results:
            for c in res["curves"] + res["peers"]:
                for p in c["points"]:
                    w.writerow([res["scene"].name, res["scene"].n, c["method"], c["seed"], p["work"], p["seconds"],
                                p["max_overlap"], p["kkt_residual"], p["W"], p["W_err"], p["A"]])


# ---- the picture ---------------------------------------------------------------------------------
def plot(res, path):
    """Rows: the error measures; columns: against wall time, against work. One colour per
    method: the median over seeds (line), min-max band (shade), the ladder's stops (markers,
    one per tolerance, at the median of the seeds)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    methods = []
    for c in res["curves"] + res["peers"]:
        if c["method"] not in methods:
            methods.append(c["method"])
    cmap = plt.get_cmap("tab10")
    colour = {m: cmap(i % 10) for i, m in enumerate(methods)}
    markers = ["o", "s", "^", "D", "v", "P"]
    fig, axes = plt.subplots(len(MEASURES), 2, figsize=(15, 3.0 * len(MEASURES)), squeeze=False)
    for col, (xkey, xlabel) in enumerate((("seconds", "wall time of the loop [s]"),
                                         ("work", "iterations (NAP/NAV: inner iterations)"))):
        xs_all = [p[xkey] for c in res["curves"] + res["peers"] for p in c["points"]
                  if p[xkey] is not None and math.isfinite(p[xkey]) and p[xkey] > 0]
        if not xs_all:
            continue
        grid = np.geomspace(min(xs_all), max(xs_all), 300)
        for row, (ykey, ylabel) in enumerate(MEASURES):
            ax = axes[row][col]
            meds = []
            for m in methods:
                cs = [c["points"] for c in res["curves"] + res["peers"] if c["method"] == m and c["points"]]
                b = band(cs, xkey, ykey, grid)
                if b is None or not np.any(np.isfinite(b[0])):
                    continue
                med, lo, hi = b
                meds.append(med[np.isfinite(med)])
                peer = any(c["method"] == m for c in res["peers"])
                ax.plot(grid, med, color=colour[m], lw=1.8, ls="--" if peer else "-", label=m)
                ax.fill_between(grid, lo, hi, color=colour[m], alpha=0.13, lw=0)
                for k, eps in enumerate(res["tols"]):
                    rs = [r for r in res["runs"] if r["method"] == m and r["eps"] == eps]
                    x = _median([r["seconds" if xkey == "seconds" else "work"] for r in rs])
                    y = _median([r[ykey] for r in rs])
                    if math.isfinite(x) and math.isfinite(y) and grid[0] <= x <= grid[-1]:
                        ax.plot([x], [max(y, FLOOR)], marker=markers[k % len(markers)], color=colour[m], ms=7,
                                mec="black", mew=0.7, ls="none", zorder=5)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlim(grid[0], grid[-1])
            if meds:
                v = np.concatenate(meds)
                v = v[v > FLOOR]
                if v.size:  # the medians decide the range; bands and zeros may leave it
                    ax.set_ylim(max(v.min() / 10, 1e-16), v.max() * 3)
            else:
                ax.text(0.5, 0.5, "no data", transform=ax.transAxes, ha="center")
            ax.grid(True, which="major", alpha=0.3)
            if row == len(MEASURES) - 1:
                ax.set_xlabel(xlabel)
            if col == 0:
                ax.set_ylabel(ylabel)
            if ykey == "max_overlap":
                ax.axhline(1e-3, color="grey", lw=0.9, ls=":")
            if ykey == "kkt_residual":
                ax.axhline(1e-2, color="grey", lw=0.9, ls=":")
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], color=colour[m], lw=2, ls="--" if any(c["method"] == m for c in res["peers"]) else "-")
               for m in methods]
    labels = list(methods)
    handles += [Line2D([], [], marker=markers[k % len(markers)], color="lightgrey", mec="black", ls="none", ms=7)
                for k in range(len(res["tols"]))]
    labels += [f"stopped by (4.3) at eps = {e:g}" for e in res["tols"]]
    handles.append(Line2D([], [], color="grey", lw=0.9, ls=":"))
    labels.append("certificate's tolerance")
    fig.legend(handles, labels, loc="center right", fontsize=9, frameon=False, bbox_to_anchor=(1.0, 0.5))
    nseeds = len({c["seed"] for c in res["curves"]})
    fig.suptitle(f"{res['label']}: error against work, median over {nseeds} seeds (shade: min-max)", fontsize=12)
    fig.tight_layout(rect=(0, 0, 0.8, 0.97))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


# ---- command line ----------------------------------------------------------------------------------
QUICK = {"scenes": [("paper-2d", ["n=7"], 5000), ("paper-2d", ["n=100"], 20000)], "tolerances": [1e-4, 1e-6],
         "seeds": [1, 2]}


def main(args):
    from .. import config
    from mpipack.parallel.launcher import world_size
    if world_size() > 1:
        print("mpipack: error: start mpipack compare without mpirun (its runs are on one rank each)",
              file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    try:
        if args.quick:
            if args.scene is not None:
                raise CompareError("--quick runs its own scenes (N = 7 and N = 100); give no SCENE with it")
            scenes = [(src, sets + list(args.overrides), mi) for src, sets, mi in QUICK["scenes"]]
            tols = parse_floats(args.tolerances, "--tolerances") if args.tolerances else QUICK["tolerances"]
            seeds = parse_seeds(args.seeds, QUICK["seeds"])
        else:
            scene = config.load(args.scene, args.overrides)
            scenes = [(args.scene, list(args.overrides), scene.stop.max_iter)]
            tols = parse_floats(args.tolerances, "--tolerances") if args.tolerances else \
                ([1e-4, 1e-6, 1e-8] if scene.n < 1000 else [1e-4, 1e-5])
            seeds = parse_seeds(args.seeds, [1, 2, 3, 4, 5] if scene.n < 1000 else [1, 2, 3])
        peers = [p for spec in args.peer for p in read_peer(spec)]
        plans = []
        for src, sets, mi in scenes:
            sc = config.load(src, sets)
            plans.append((src, sets, mi, sc, parse_methods(args.methods, sc)))
    except (CompareError, config.SceneError) as e:
        print(f"mpipack: error: {e}", file=sys.stderr)
        return 2
    out = args.out or os.path.join("mpipack-out", "compare-quick" if args.quick else "compare")
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:
        print(f"mpipack: error: --out: cannot create {out}: {e.strerror}", file=sys.stderr)
        return 2
    results, pngs = [], []
    for src, sets, mi, sc, methods in plans:
        print(f"mpipack compare: {sc.name} N = {sc.n} ({sc.dim}D): {len(methods)} methods x {len(tols)} "
              f"tolerances x {len(seeds)} seeds", flush=True)
        res = compare_scene(src, sets, methods, tols, seeds, out, mi, lambda s: print(s, flush=True))
        for label, seed, n, rows in peers:
            if n is not None and n != sc.n:
                continue
            pts = [{"work": r["work"], "seconds": r["wall_seconds"], "max_overlap": r["max_overlap"],
                    "kkt_residual": r["kkt_residual"], "W": r["W"], "A": r["A"],
                    "W_err": _werr(r["W"], res["wref"].get(seed, next(iter(res["wref"].values()), math.nan)))}
                   for r in rows]
            res["peers"].append({"method": label, "seed": seed, "points": pts})
        png = os.path.join(out, f"work_precision_{_slug(sc.name)}_n{sc.n}.png")
        plot(res, png)
        results.append(res)
        pngs.append(png)
    write_csv(results, out)
    text = markdown(results, ", ".join(f"{t:g}" for t in sorted(tols, reverse=True)), seeds,
                    time.perf_counter() - t0, pngs)
    with open(os.path.join(out, "compare.md"), "w") as f:
        f.write(text + "\n")
    print(text, flush=True)
    print(f"mpipack compare: {out}/compare.md, {', '.join(os.path.basename(p) for p in pngs)}, ladder.csv, curves.csv",
          flush=True)
    return 0
