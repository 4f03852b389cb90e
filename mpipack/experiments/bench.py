"""``mpipack bench``: particle-iterations per second per rank and resident bytes per particle.

The benchmark starts from a packed state: the N lattice points (triangular in 2D, FCC in 3D)
nearest the origin, spacing 0.99 d, so each sphere overlaps its lattice neighbours by 1% and,
from the second iteration on, every contact carries a multiplier: the most work a pair row
can ask for (every branch taken). Small alpha and beta keep the lattice in place during the
timed loop, so the figure is the steady cost of an iteration near convergence, without the
rebuilds of the expansion phase (those are counted and printed). The kernel's work per pair
does not depend on the parameter values.

Figures (median over repeats of the timed loop, all ranks in lock step):
    particle-iterations / s / rank = N * iterations / (loop seconds * ranks)
    bytes / particle = (resident set after set-up - resident set before) / local particles,
                       the largest over ranks (interpreter, numba and MPI are not counted)
"""

import ctypes
import gc
import json
import os
import resource
import time

import numpy as np

PARAMS = dict(alpha=1e-3, beta=1.0, gamma=1e-3)


def _rss_bytes():
    """Resident set size now, after returning freed heap pages to the system."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _state_bytes(solver):
    """Bytes held by the rank's particle arrays and pair store (what the RSS figure should be)."""
    st = solver.state
    arrays = (st.x, st.x_prev, st.x_new, st.gid, st.diam, st.x_build, st.pair_offsets, st.pair_j,
              st.pair_lambda)
    return sum(a.nbytes for a in arrays)


def bench_case(comm, dim, n, form="S", iters=None, repeats=3, spacing=0.99, seed=1):
    """Run one case; returns a dict of figures (identical on every rank).

    One ``engine.loop.run`` with a timing hook: 3 warm-up iterations, 5 to size the timed loops
    (about 2 s each) unless ``iters`` is given, then ``repeats`` timed loops, each between two
    barriers; the hook stops the run after the last one.
    """
    from mpipack import config
    from mpipack.engine import hooks
    from mpipack.engine.loop import run

    p = PARAMS
    overrides = [f"dim={dim}", f"n={n}", "init.kind=lattice", f"init.spacing={spacing}",
                 f"method.form={form}", f"method.alpha={p['alpha']}", f"method.beta={p['beta']}",
                 f"method.gamma={p['gamma']}", "stop.eps=0", "stop.max_iter=1000000000", f"seed={seed}"]
    scene = config.load("default", overrides)
    # compile (or load) this case's kernels first, so that the memory figure holds no code
    run(config.load("default", overrides[:1] + ["n=64", "stop.max_iter=1"] + overrides[2:-2]), comm)
    comm.barrier()
    fig = {"rss0": _rss_bytes()}
    plan = {"iters": iters, "rates": [], "next": 3, "what": "warm"}

    def start_clock(it, length, what):
        comm.barrier()
        plan.update(t=time.perf_counter(), next=it + length, what=what)

    def timed(ctx):
        it = ctx.iteration
        if it != plan["next"]:
            return None
        if plan["what"] == "calibrate":  # 5 iterations size the timed loops
            dt = comm.allreduce(np.array([time.perf_counter() - plan["t"]]), op="max")[0] / 5
            plan["iters"] = int(max(10, min(2000, 2.0 / max(dt, 1e-9))))
        elif plan["what"] == "timed":
            dt = comm.allreduce(np.array([time.perf_counter() - plan["t"]]), op="max")[0]
            plan["rates"].append(n * plan["iters"] / dt / comm.size)
            if len(plan["rates"]) == repeats:
                return hooks.STOP
        if plan["iters"] is None:
            start_clock(it, 5, "calibrate")
        else:
            plan.setdefault("rebuilds0", ctx.solver.counters["rebuilds"])
            start_clock(it, plan["iters"], "timed")
        return None

    def after_setup(ctx):
        fig["rss1"] = _rss_bytes()
        st = ctx.solver.state
        n_local = max(st.n_local, 1)
        fig["bpp"] = comm.allreduce(np.array([(fig["rss1"] - fig["rss0"]) / n_local]), op="max")[0]
        fig["apb"] = comm.allreduce(np.array([_state_bytes(ctx.solver) / n_local]), op="max")[0]

    solver, res = run(scene, comm, hooks=[hooks.Hook(after_setup, at_start=True),
                                          hooks.Hook(timed, every=1, name="bench")])
    rates = plan["rates"]
    peak = comm.allreduce(np.array([resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0]), op="max")[0]
    st = solver.state
    pairs = comm.allreduce(np.array([st.pair_offsets[-1]], dtype=np.int64), op="sum")[0]
    return {
        "dim": dim, "n": n, "ranks": comm.size, "form": form, "iterations": plan["iters"],
        "repeats": repeats,
        "rate_per_rank_median": float(np.median(rates)),
        "rate_per_rank_all": [float(r) for r in rates],
        "bytes_per_particle": float(fig["bpp"]),
        "array_bytes_per_particle": float(fig["apb"]),
        "peak_rss_mb": float(peak / 2**20),
        "setup_seconds": float(comm.allreduce(np.array([res["setup_seconds"]]), op="max")[0]),
        "row_entries_per_particle": float(pairs) / n,
        "rebuilds_in_timed_loops": solver.counters["rebuilds"] - plan["rebuilds0"],
    }


def main(args):
    from mpipack.parallel.comm import Comm
    comm = Comm()
    dims = args.dim or [2, 3]
    ns = [int(v) for v in (args.n or [1e4, 1e5, 1e6])]
    rows = []
    if comm.rank == 0:
        print(f"mpipack bench: {comm.size} rank(s), form {args.form}, lattice start spacing 0.99 d")
        print(f"{'dim':>3} {'N':>9} {'iters':>6} {'Mpart-it/s/rank':>16} {'RSS B/part':>11} "
              f"{'arrays B/part':>13} {'entries/part':>12} {'setup s':>8} {'peak MB':>8}", flush=True)
    for dim in dims:
        for n in ns:
            r = bench_case(comm, dim, n, form=args.form, iters=args.iters)
            rows.append(r)
            if comm.rank == 0:
                print(f"{dim:>3} {n:>9} {r['iterations']:>6} {r['rate_per_rank_median'] / 1e6:>16.2f} "
                      f"{r['bytes_per_particle']:>11.0f} {r['array_bytes_per_particle']:>13.0f} "
                      f"{r['row_entries_per_particle']:>12.1f} "
                      f"{r['setup_seconds']:>8.2f} {r['peak_rss_mb']:>8.0f}", flush=True)
    if comm.rank == 0 and args.json:
        with open(args.json, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
    return 0
