"""mpipack side of the peer benchmark: the same start and finish line as lammps_fire.py.

    python tools/peers/mpipack_side.py START.npz --ranks 1 --json OUT.json [--mode ladder]

START.npz is a start made by ``make_start`` (compare.py does it); its sidecar START.json
holds the scene settings (n, dim, init.sigma, seed) that made it, so mpipack regenerates the
same start itself (its generator is a pure function of seed and global id).

Everything that knows mpipack's command line is in this file's first section
(``mpipack_command``, ``mpipack_env``, ``scene_sets``, ``run_mpipack``, ``make_start``,
``CERTIFIED_SETS``): when the CLI changes, change it there.

Modes (the finish line is score.at_finish_line, exactly as for LAMMPS):

- ``ladder`` (default): mpipack runs with a fixed iteration budget (stop.eps = 0) at budgets
  n0 r^k (r = 1.5^(1/3), so the look-back of 1/3 of the run spans 3 budget intervals, as
  score.settled asks); each run is scored from its dump, and the first budget at the finish
  line gives the time: the loop_seconds of that run (start-up excluded, as for LAMMPS).
  mpipack is deterministic, so the run with budget n passes through the states of the
  shorter ones. Costs about 1/(1 - 1/r) ~ 8 times the final run; use it at small N. With
  ``--chain`` each budget continues the previous budget's checkpoint (``mpipack run
  --restart``, the same trajectory bit for bit): one run's cost plus a start-up per budget,
  the time being the segments' loop seconds added up (each less its checkpoint write).
- ``budget``: one run with --budget iterations, scored; "reached" says whether the end state
  is at the finish line by overlap (W settledness cannot be judged from one state: it is
  reported as unknown unless --verify runs a 1.5x longer budget to compare W).
- ``certified``: mpipack stops itself by its own certified criterion (CERTIFIED_SETS); its dump is scored and the finish line checked
  (overlap here, W with --verify: a second run at 1.5x the iterations; its W within 0.5%).
"""

import argparse
import json
import math
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)
import score  # noqa: E402

# ==== everything that knows mpipack's command line =============================================

# The certified stop (issue 14, "A stop that certifies what it claims"): the --set overrides
# that make `mpipack run` stop by itself at a certified packing (max overlap <= 1e-3 d, KKT
# residual <= 1e-2, W settled to 1e-4 over the last tenth of the run: the defaults), with no
# iteration bound in the way.
CERTIFIED_SETS = ["stop.rule=certified", "stop.max_iter=100000000"]


def mpipack_command():
    """The mpipack executable as an argv prefix: $MPIPACK_CMD (e.g. "python -m mpipack.cli")
    or the project's .venv/bin/mpipack."""
    cmd = os.environ.get("MPIPACK_CMD")
    if cmd:
        return shlex.split(cmd)
    return [os.path.join(REPO, ".venv", "bin", "mpipack")]


def mpipack_env():
    """The environment of tools/env.sh (venv first on PATH, Open MPI may run as root and
    oversubscribe), without the LAMMPS venv's MPICH (its lib/ on LD_LIBRARY_PATH or its
    bin/ with an MPICH mpirun on PATH would break Open MPI's mpi4py)."""
    env = dict(os.environ)
    lammps_venv = os.path.join(HERE, ".venv-lammps")

    def clean(var):
        parts = [p for p in env.get(var, "").split(os.pathsep)
                 if p and not os.path.abspath(p).startswith(lammps_venv)]
        if parts:
            env[var] = os.pathsep.join(parts)
        else:
            env.pop(var, None)

    clean("LD_LIBRARY_PATH")
    clean("PATH")
    env["PATH"] = os.path.join(REPO, ".venv", "bin") + os.pathsep + env.get("PATH", "")
    env["VIRTUAL_ENV"] = os.path.join(REPO, ".venv")
    if os.geteuid() == 0:
        env["OMPI_ALLOW_RUN_AS_ROOT"] = "1"
        env["OMPI_ALLOW_RUN_AS_ROOT_CONFIRM"] = "1"
    env.setdefault("OMPI_MCA_rmaps_base_oversubscribe", "1")
    for k in ("LAMMPS_VENV", "LAMMPS_PYTHON", "LAMMPS_MPIEXEC"):
        env.pop(k, None)
    return env


def mpirun_prefix(ranks, env):
    """[] for one rank (mpipack runs as a singleton), else Open MPI's mpirun -n R."""
    if ranks == 1:
        return []
    mpirun = shutil.which("mpirun", path=env["PATH"])
    if mpirun is None:
        raise SystemExit("mpipack_side: no mpirun (Open MPI) on PATH")
    return [mpirun, "-n", str(ranks)]


def scene_sets(n, dim, sigma):
    """--set overrides for the start: n spheres of diameter 1 in dim dimensions, Gaussian of
    std sigma (the default scene otherwise)."""
    return [f"n={n}", f"dim={dim}", f"init.sigma={sigma!r}"]


def run_mpipack(start_meta, ranks, out_dir, dump, sets=(), timeout=None, restart=None):
    """One `mpipack run` of the start's scene with extra --set overrides (with ``restart``, a
    run folder: continue its checkpoint, bit for bit the uninterrupted run's trajectory).
    Returns (exit code, summary dict or None, seconds of the whole process, stderr tail)."""
    env = mpipack_env()
    argv = mpirun_prefix(ranks, env) + mpipack_command() + ["run"]
    if restart is not None:
        argv += ["--restart", restart]
    for s in scene_sets(start_meta["n"], start_meta["dim"], start_meta["sigma"]) + list(sets):
        argv += ["--set", s]
    argv += ["--seed", str(start_meta["seed"]), "--out", out_dir, "--quiet"]
    if restart is None or os.path.realpath(restart) != os.path.realpath(out_dir):
        argv += ["--overwrite"]  # this harness's own folders
    if dump:
        argv += ["--dump", dump]
    t0 = time.perf_counter()
    try:
        p = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=timeout)
        rc, err = p.returncode, p.stderr
    except subprocess.TimeoutExpired as e:
        rc, err = "timeout", (e.stderr or b"").decode(errors="replace") if isinstance(e.stderr, bytes) else (e.stderr or "")
    wall = time.perf_counter() - t0
    summary = None
    path = os.path.join(out_dir, "summary.json")
    if rc != "timeout" and os.path.exists(path):
        with open(path) as f:
            summary = json.load(f)
    return rc, summary, wall, err[-2000:]


def budget_sets(iters):
    """A fixed iteration budget: run exactly `iters` iterations. The default scene stops by
    its certificate (stop.rule = "certified"), which would end every budget past the certified
    stop at the same state: the paper's rule (4.3) with eps = 0 never fires."""
    return [f"stop.max_iter={int(iters)}", "stop.rule=eps", "stop.eps=0"]


def loop_seconds(summary):
    """The timed part of a run (iterations only; set-up and the dump excluded)."""
    return float(summary["loop_seconds"])


def iterations(summary):
    return int(summary["iterations"])


def make_start(n, dim, sigma, seed, path, method="run", ranks=1, timeout=None):
    """Write the start (x, diam in gid order) to ``path`` and its scene settings to the
    sidecar path.replace('.npz', '.json'). method "run": `mpipack run` with 0 iterations and
    --dump; "module": mpipack's own generator functions called from its venv's python (no
    neighbour build: for starts too dense for `run`'s pair rows)."""
    meta = {"n": int(n), "dim": int(dim), "sigma": float(sigma), "seed": int(seed), "method": method}
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    if method == "run":
        with tempfile.TemporaryDirectory() as tmp:
            dump = os.path.join(tmp, "start.npz")
            rc, summary, _, err = run_mpipack(meta, ranks, tmp, dump, sets=budget_sets(0), timeout=timeout)
            if not os.path.exists(dump):
                raise SystemExit(f"make_start: mpipack run failed (exit {rc}): {err}")
            d = np.load(dump)
            np.savez(path, x=d["x"], diam=d["diam"])
    elif method == "module":
        # the Gaussian of mpipack.engine.initial (a pure function of seed and gid), unit diameters (the
        # default scene's particles.diameter = 1): the scene `run` would make
        code = (
            "import sys, numpy as np\n"
            "from mpipack.engine import initial as init\n"
            "n, dim, sigma, seed, path = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), int(sys.argv[4]), sys.argv[5]\n"
            "gids = np.arange(n, dtype=np.int64)\n"
            "x = init.gaussian(seed, gids, dim, sigma, np.zeros(dim))\n"
            "np.savez(path, x=x, diam=np.ones(n))\n")
        env = mpipack_env()
        py = os.path.join(os.path.dirname(mpipack_command()[0]), "python")
        if os.environ.get("MPIPACK_PYTHON"):
            py = os.environ["MPIPACK_PYTHON"]
        p = subprocess.run([py, "-c", code, str(n), str(dim), repr(float(sigma)), str(seed), path],
                           env=env, capture_output=True, text=True, timeout=timeout)
        if p.returncode != 0:
            raise SystemExit(f"make_start (module): {p.stderr[-2000:]}")
    else:
        raise ValueError(method)
    with open(path[:-4] + ".json", "w") as f:
        json.dump(meta, f)
    return meta


# ==== the benchmark side ===========================================================================

def scored_run(meta, ranks, iters, workdir, timeout, sets=None, chain=False):
    """Run a budget (or the given sets), score the dump; a record or an error record.

    With ``chain`` the budgets share one run folder, ``workdir/chain``: a budget continues
    the previous budget's checkpoint (written when a budget ends at stop.max_iter) instead of
    starting again, so a ladder costs one run; its "seconds" are then that segment's loop
    seconds only (the caller adds them up)."""
    tag = f"it{iters}" if iters is not None else "run"
    out = os.path.join(workdir, "chain" if chain else tag)
    dump = os.path.join(workdir, f"{tag}.npz")
    restart = out if chain and os.path.exists(os.path.join(out, "checkpoint.h5")) else None
    run_sets = list(sets if sets is not None else budget_sets(iters))
    if chain:
        # a budget run ends with exit 0 and no checkpoint: ask for one at its last iteration
        run_sets.append(f"output.checkpoint_every={int(iters)}")
    rc, summary, wall, err = run_mpipack(meta, ranks, out, dump, sets=run_sets,
                                         timeout=timeout, restart=restart)
    if summary is None or not os.path.exists(dump):
        return {"iterations": iters, "error": f"exit {rc}", "stderr": err}
    if sets is None and iterations(summary) != iters:
        # a budget runs whole: the ladder passes through the states of the shorter budgets
        os.remove(dump)
        return {"iterations": iters, "error": f"budget {iters} stopped at {iterations(summary)} iterations",
                "stderr": err}
    d = np.load(dump)
    fig = score.score(d["x"], d["diam"])
    os.remove(dump)
    seconds = loop_seconds(summary)
    if chain:
        # the checkpoint that the next budget continues from is written inside the loop; the
        # uninterrupted run would not write it
        ck = summary.get("checkpoint") or {}
        if ck.get("iteration") != iters:
            return {"iterations": iters, "error": f"budget {iters} left no checkpoint to continue", "stderr": err}
        seconds -= float(ck.get("write_seconds") or 0.0)
    return {"iterations": iterations(summary), "seconds": seconds,
            "setup_seconds": summary.get("setup_seconds"), "process_seconds": wall,
            "exit": rc, "converged": summary.get("converged"), "summary_max_overlap": summary.get("max_overlap"),
            "restart_from": summary.get("restart_from"),
            "final": fig}


def ladder(meta, ranks, args, workdir):
    r = args.ratio
    budgets = []
    b = float(args.n0)
    while b <= args.max_iter:
        k = int(round(b))
        if not budgets or k > budgets[-1]:
            budgets.append(k)
        b *= r
    runs, its, Ws = [], [], []
    t_start = time.perf_counter()
    chained = 0.0  # --chain: the loop seconds of the segments before this one
    if args.chain:
        shutil.rmtree(os.path.join(workdir, "chain"), ignore_errors=True)  # never continue an old run
    for k in budgets:
        if args.ladder_wall_limit and time.perf_counter() - t_start > args.ladder_wall_limit:
            return runs, None, "ladder_wall_limit"
        if runs and args.time_limit and runs[-1].get("seconds", 0.0) > args.time_limit:
            return runs, None, "time_limit"
        rec = scored_run(meta, ranks, k, workdir, args.run_timeout, chain=args.chain)
        if args.chain and "seconds" in rec:
            rec["segment_seconds"] = rec["seconds"]
            chained += rec["seconds"]
            rec["seconds"] = chained
        runs.append(rec)
        if args.verbose:
            f = rec.get("final", {})
            print(f"iterations {k:8d} loop {rec.get('seconds', math.nan):8.2f}s overlap "
                  f"{f.get('max_overlap', math.nan):.3e} W/N2 {f.get('W_over_N2', math.nan):.6f}", flush=True)
        if "error" in rec:
            return runs, None, rec["error"]
        its.append(rec["iterations"])
        Ws.append(rec["final"]["W"])
        if score.at_finish_line(rec["final"], its, Ws, args.overlap_tol, args.w_tol, args.lookback, args.window):
            return runs, rec, "finish_line"
    return runs, None, "max_iter"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("start", help="start .npz made by make_start (with its .json sidecar)")
    p.add_argument("--ranks", type=int, default=1)
    p.add_argument("--mode", choices=["ladder", "budget", "certified"], default="ladder")
    p.add_argument("--budget", type=int, default=20000, help="--mode budget: iterations")
    p.add_argument("--n0", type=int, default=500, help="--mode ladder: first budget")
    p.add_argument("--ratio", type=float, default=1.5 ** (1.0 / 3.0), help="--mode ladder: budget ratio")
    p.add_argument("--chain", action="store_true",
                   help="--mode ladder: each budget continues the previous one's checkpoint (one run's "
                        "cost instead of ~8; the time is the sum of the segments' loop seconds)")
    p.add_argument("--max-iter", type=int, default=2_000_000)
    p.add_argument("--overlap-tol", type=float, default=score.OVERLAP_TOL)
    p.add_argument("--w-tol", type=float, default=score.W_TOL)
    p.add_argument("--lookback", type=float, default=score.LOOKBACK)
    p.add_argument("--window", type=int, default=score.W_WINDOW)
    p.add_argument("--verify", action="store_true",
                   help="budget/certified: also run 1.5x the iterations and compare W (not timed)")
    p.add_argument("--run-timeout", type=float, default=None, help="seconds per mpipack process")
    p.add_argument("--time-limit", type=float, default=None,
                   help="ladder: no longer budget once a run's loop took this many seconds (as lammps_fire.py's)")
    p.add_argument("--ladder-wall-limit", type=float, default=None, help="ladder: wall seconds for all its runs")
    p.add_argument("--workdir", default=None)
    p.add_argument("--json", default=None)
    p.add_argument("-v", "--verbose", action="store_true")
    args = p.parse_args(argv)
    with open(args.start[:-4] + ".json") as f:
        meta = json.load(f)
    workdir = args.workdir or tempfile.mkdtemp(prefix="mpipack-side-")
    os.makedirs(workdir, exist_ok=True)
    out = {"code": "mpipack", "ranks": args.ranks, "n": meta["n"], "dim": meta["dim"],
           "start": os.path.abspath(args.start), "mode": args.mode,
           "command": " ".join(mpipack_command())}
    if args.mode == "ladder":
        runs, hit, reason = ladder(meta, args.ranks, args, workdir)
        last = hit or (runs[-1] if runs else {})
        out.update({"reached": hit is not None, "stop_reason": reason,
                    "seconds": last.get("seconds"), "iterations": last.get("iterations"),
                    "final": last.get("final"),
                    "ladder": [{k: r.get(k) for k in ("iterations", "seconds", "error")} |
                               {"max_overlap": r.get("final", {}).get("max_overlap"),
                                "W_over_N2": r.get("final", {}).get("W_over_N2")} for r in runs],
                    "protocol": {"ratio": args.ratio, "n0": args.n0, "chain": args.chain, "lookback": args.lookback,
                                 "window": args.window, "w_tol": args.w_tol, "overlap_tol": args.overlap_tol}})
    else:
        if args.mode == "certified":
            if CERTIFIED_SETS is None:
                raise SystemExit("mpipack_side: --mode certified needs CERTIFIED_SETS (mpipack_side.py) "
                                 "filled in with the certified stop's --set overrides")
            rec = scored_run(meta, args.ranks, None, workdir, args.run_timeout, sets=CERTIFIED_SETS)
        else:
            rec = scored_run(meta, args.ranks, args.budget, workdir, args.run_timeout)
        if "error" in rec:
            out.update({"reached": False, "stop_reason": rec["error"], "stderr": rec.get("stderr")})
        else:
            ok_overlap = rec["final"]["max_overlap"] <= args.overlap_tol
            out.update({"seconds": rec["seconds"], "iterations": rec["iterations"], "final": rec["final"],
                        "setup_seconds": rec["setup_seconds"], "exit": rec["exit"],
                        "converged": rec["converged"]})
            w_ok = None
            if args.verify:
                more = scored_run(meta, args.ranks, int(math.ceil(1.5 * rec["iterations"])), workdir, args.run_timeout)
                if "error" not in more:
                    change = (more["final"]["W"] - rec["final"]["W"]) / more["final"]["W"]
                    w_ok = abs(change) <= args.w_tol
                    out["verify"] = {"iterations": more["iterations"], "final": more["final"],
                                     "W_rel_change_after_stop": change}
            out["reached"] = bool(ok_overlap and (w_ok is not False))
            out["w_settled_checked"] = w_ok is not None
            out["stop_reason"] = "finish_line" if out["reached"] else "overlap" if not ok_overlap else "W not settled"
    text = json.dumps(out)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")
    print(text, flush=True)
    return 0 if out.get("reached") else 4


if __name__ == "__main__":
    sys.exit(main())
