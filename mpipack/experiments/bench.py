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

``mpipack bench --phases`` times instead the phases a default run spends its time in, on the
packed state of a real default run (``PHASES_DOC`` below, ``phases_case``).
"""

import ctypes
import gc
import json
import math
import os
import resource
import time

import numpy as np

from mpipack.jit import njit

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
              st.pair_lambda) + (st.pair_work or ())
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
    if getattr(args, "phases", False):
        return phases_main(args, comm)
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


# ---- the phases of a default run (``mpipack bench --phases``) --------------------------------

PHASES_DOC = """The phases of a default run, per sphere-iteration, on a packed state.

The state: the default scene (fire-al schedule, S form) in 2D or 3D run from its usual start
to its end (the certificate, or ``run_iters`` iterations; the bench says which), so that the
pair rows, the multipliers and the L-BFGS memory are those the last iterations of a real run
work on. Each phase is then timed on that state (every rank in lock step, a barrier before each
repetition, the slowest rank's time; the median of ``repeats`` repetitions, each a loop of
calls long enough to take about ``target`` seconds):

    fire          the fire-al kernel's FIRE pass with its continuous dual step
                  (``kernels.fire``: update_lambda, all sums; coefficients of the soft phase,
                  beta = OMEGA c_b at the start's c_b), no reduction
    fire_nodual   the same pass without the dual step (update_lambda False)
    dual          fire - fire_nodual: what the dual step costs inside the pass (it is fused)
    fire_norows   the fire pass over empty pair rows (every offset 0, no half list): the per-sphere part
    pair_loop     fire - fire_norows: the pair rows' part of the pass
    alm           the multiplier (ALM) step: one pass with the penalty off, beta = c_b
    grad          L-BFGS's gradient pass (the kernel as a gradient pass, the stiff phase's
                  coefficients: no X^{n-1}, of the sums only |X^n|^2, no gain or row)
    dots          ``kernels.lbfgs.dots``: the gradient's dots with the 2m + 1 memory slots
    direction     ``kernels.lbfgs.direction`` with every memory slot in use (its worst case)
    reduce        the L-BFGS iteration's ONE allreduce (its exact sums, maxima, counts)
    two_loop      ``methods.lbfgs.LBFGS.direction``: the two-loop recursion on the Gram
                  matrix (scalars, the same on every rank)
    lbfgs         grad + dots + direction + reduce + two_loop: an L-BFGS iteration
    metrics       ``stop.measures.measure`` (overlap_a False, as the certificate calls it),
                  with its reduction
    fit_step      one step of the certificate's multiplier fit (``stop.fit``): (time of
                  best_kkt with K steps - with 0 steps) / K
    build         the pair rows built again from the state's positions and history
                  (``parallel.neighbors.build_rows``, the state's skin) and the fire-al pass's
                  half list made from them (``kernels.fire.pair_work``): a rebuild's rows, not
                  its exchange, borders or the locals' cell order
    iteration     ``Solver.step`` as the loop runs it from the packed state (the schedule's
                  own choice of pass, the reduction, ghosts, rebuilds when due); timed last,
                  the state moves on

ns / sphere = seconds per call x ranks / N (the core time per sphere), by the process's CPU
clock (on a shared machine the wall clock also counts the time other processes held the core;
both are reported, ``ns_per_sphere`` and ``ns_per_sphere_wall``).

Bytes a pass must move per sphere and per pair entry (b the dimension, float64 8 bytes,
pair_j int32 4, offsets int64 8; the neighbours' x_j and d_j, gathered in cell order, are
taken to come from cache, so these are the least traffic, STREAM's convention: a write
counted once):

    fire, alm         sphere 24 b + 16  (x, x_prev, x_new written, d_i, offset)
                      entry  74: the half list's entries (half of them: entry, partner and
                      mirror 20, lambda read 8 and written to both entries 16, the three
                      terms g, gain, row written to both 48), then every entry's pair_j and
                      terms read (28); fire_nodual (no dual step) 66
    grad              sphere 16 b + 16 (x, x_new written, d_i, offset); entry 14 + 16 b (no
                      dual step; the force's b components written to both entries, read)
    dots              sphere 8 b (2 + K), K = 2m + 1 memory slots (x, x_new, every slot)
    direction         sphere 8 b 17 (x, x_new, 11 slots read; 3 slots and x_new written)
    metrics           sphere 8 b + 44 (x, d, gid, offset; pressure, contacts, |g_i| written)
                      entry  12 (pair_j, lambda)
    fit_step          sphere 32 b + 16 (x and r in each of its two passes, offsets)
                      contact row 72 (c_j, m, m_prev, g read and written over the two passes)

MB/s = those bytes / time, against the machine's bandwidth measured in the same session by a
STREAM triad (a_i = b_i + s c_i over three arrays of 2^25 float64, 768 MiB in all, beyond the
last-level cache; 24 bytes per element, one thread, best of 5): the fraction says how far a
phase is from being bound by memory traffic. The same triad on 2^20-element arrays (24 MiB, in
the last-level cache, where a packing of 1e4 - 1e5 spheres lives) is reported beside it.
"""

_TRIAD_N = 1 << 25
_TRIAD_CACHED_N = 1 << 20


@njit(cache=True)
def _triad(a, b, c, s):
    for i in range(a.shape[0]):
        a[i] = b[i] + s * c[i]


def triad_bandwidth(n=_TRIAD_N, repeats=5):
    """Bytes per second of one thread's STREAM triad over arrays of ``n`` float64 (best of
    ``repeats``; 24 n bytes per sweep)."""
    b = np.full(n, 1.0)
    c = np.full(n, 2.0)
    a = np.empty(n)
    _triad(a, b, c, 3.0)  # compile and touch the pages
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        _triad(a, b, c, 3.0)
        best = min(best, time.perf_counter() - t0)
    return 24.0 * n / best


class Timing(tuple):
    """(wall, cpu): median seconds per call, by the wall clock and by the process's CPU
    clock (the slowest rank's of each); arithmetic is per component."""

    def __new__(cls, wall, cpu):
        return super().__new__(cls, (float(wall), float(cpu)))

    def __add__(self, other):
        return Timing(self[0] + other[0], self[1] + other[1])

    def __sub__(self, other):
        return Timing(self[0] - other[0], self[1] - other[1])

    def __truediv__(self, k):
        return Timing(self[0] / k, self[1] / k)


def _timer(comm, repeats, target):
    """A function time(fn) -> ``Timing`` of one call of fn (see PHASES_DOC)."""

    def time_it(fn):
        fn()  # warm up (compiles what is not cached)
        comm.barrier()
        t0 = time.perf_counter()
        fn()
        one = comm.allreduce(np.array([time.perf_counter() - t0]), op="max")[0]
        calls = int(max(1, min(10000, target / max(one, 1e-7))))
        wall, cpu = [], []
        for _ in range(repeats):
            comm.barrier()
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(calls):
                fn()
            dt = comm.allreduce(np.array([time.perf_counter() - t0, time.process_time() - c0]), op="max")
            wall.append(dt[0] / calls)
            cpu.append(dt[1] / calls)
        return Timing(np.median(wall), np.median(cpu))

    return time_it


def _contact_rows(st, tol):
    """Row entries of the local spheres in contact to ``tol`` (the fit's rows)."""
    n = st.n_local
    counts = np.diff(st.pair_offsets[:n + 1])
    i = np.repeat(np.arange(n), counts)
    j = st.pair_j[:st.pair_offsets[n]]
    r2 = ((st.x[i] - st.x[j]) ** 2).sum(axis=1)
    dij = 0.5 * (st.diam[i] + st.diam[j])
    return int(np.count_nonzero(r2 <= (dij * (1.0 + tol)) ** 2))


def traffic_bytes(dim, m):
    """(bytes per sphere, bytes per pair entry, bytes per contact row) of each phase (PHASES_DOC)."""
    k = 2 * m + 1
    return {
        "fire": (24 * dim + 16, 74, 0), "fire_nodual": (24 * dim + 16, 66, 0),
        "fire_norows": (24 * dim + 16, 0, 0),
        "alm": (24 * dim + 16, 74, 0), "grad": (16 * dim + 16, 14 + 16 * dim, 0),
        "dots": (8 * dim * (2 + k), 0, 0), "direction": (8 * dim * 17, 0, 0),
        "metrics": (8 * dim + 44, 12, 0), "fit_step": (32 * dim + 16, 0, 72),
    }


def packed_state(comm, dim, n, run_iters=None, seed=1):
    """The default scene run from its start to its end (or ``run_iters`` iterations):
    returns (solver, result)."""
    from mpipack import config
    from mpipack.engine.loop import run
    overrides = [f"dim={dim}", f"n={n}", f"seed={seed}"]
    if run_iters is not None:
        overrides.append(f"stop.max_iter={run_iters}")
    return run(config.load("default", overrides), comm)


def phases_case(comm, dim, n, run_iters=None, repeats=5, target=0.3, fit_steps=50, state_out=None,
                seed=1, triad_n=_TRIAD_N):
    """Time the phases of a default run on its packed state (PHASES_DOC); returns a dict
    (identical on every rank); ``triad_n``: the bandwidth triad's array length. ``state_out``: write the packed state (x, diam in gid order)
    to this .npz on rank 0 (e.g. for tools/peers/lammps_fire.py)."""
    import copy

    from mpipack.kernels import lbfgs as kernels_lbfgs
    from mpipack.methods import lbfgs
    from mpipack.methods.fire_al_schedule import OMEGA, VMAX, Coefficients
    from mpipack.parallel import neighbors
    from mpipack.stop import measures

    t0 = time.perf_counter()
    solver, res = packed_state(comm, dim, n, run_iters, seed)
    run_seconds = time.perf_counter() - t0
    st, method = solver.state, solver.method
    sched = method.schedule
    if state_out is not None:
        got = solver.gather()
        if comm.rank == 0:
            np.savez(state_out, x=got["x"], diam=got["diam"])
    nl = st.n_local
    entries = int(st.pair_offsets[nl])
    contact_rows = _contact_rows(st, solver.scene.stop.overlap)
    totals = comm.allreduce(np.array([entries, contact_rows], dtype=np.int64), op="sum")
    time_it = _timer(comm, repeats, target)
    kern = method.kernel
    red = solver.loop_reduction()
    lam0 = st.pair_lambda.copy()
    s, d = sched.s, sched.d
    cb = s.cb
    a = 1.0 - s.mix
    b = s.dt * s.dt
    coeffs = {
        "fire": Coefficients(1.0 + a, -a, b, b * cb, OMEGA * sched.cb_start, sched.lam_floor, True, True, VMAX * d),
        "alm": Coefficients(1.0 + a, -a, b, 0.0, cb, sched.lam_floor, True, True, VMAX * d),
        "grad": Coefficients(1.0, 0.0, 1.0, cb, 0.0, sched.lam_floor, True, True, 0.0),
    }

    from mpipack.kernels import fire as kernels_fire
    mirror = neighbors.find_mirrors(nl, st.gid, st.pair_offsets, st.pair_j)
    pairs = [kernels_fire.pair_work(dim, nl, st.pair_offsets, st.pair_j, st.pair_lambda, mirror)]

    def kernel_call(c, update, gradient_pass=False):
        def call():
            red.begin()
            # (a gradient pass reads no X^{n-1}: x_prev is x, as ``FireAL.lbfgs_iteration`` has it)
            kern(st.x, st.x if gradient_pass else st.x_prev, st.x_new, nl, st.diam, st.pair_offsets, st.pair_j,
                 st.pair_lambda, pairs[0], st.walls, st.wall_lambda, solver.xbar, solver.pot, *c, update,
                 red.acc("step"), red.maxima("step"), gradient_pass)
        return call

    sec = {}
    sec["fire"] = time_it(kernel_call(coeffs["fire"], True))
    sec["fire_nodual"] = time_it(kernel_call(coeffs["fire"], False))
    offsets, work = st.pair_offsets, pairs[0]
    st.pair_offsets, pairs[0] = np.zeros_like(offsets), kernels_fire.WHOLE_ROWS
    try:
        sec["fire_norows"] = time_it(kernel_call(coeffs["fire"], True))
    finally:
        st.pair_offsets, pairs[0] = offsets, work
    sec["alm"] = time_it(kernel_call(coeffs["alm"], True))
    st.pair_lambda[:] = lam0
    sec["grad"] = time_it(kernel_call(coeffs["grad"], True, gradient_pass=True))
    st.pair_lambda[:] = lam0
    # the L-BFGS memory: the run's, or zeros of its shape (a run that ended before L-BFGS)
    lb = sched.lbfgs
    k = lbfgs.slots(lb.m)
    if st.qn is None or st.qn.shape[1] != k or st.qn.shape[0] != nl:
        st.qn = np.zeros((nl, k, dim))
    cap = lbfgs.TRUST * d
    qred = method._lbfgs_red(solver)
    sec["dots"] = time_it(lambda: kernels_lbfgs.dots(st.x, st.x_new, nl, st.qn, 0, cap, qred.begin().acc("qn"),
                                                     qred.maxima("qn")))
    coef = np.full(k, 0.1)  # every slot in use: the direction's most work
    sec["direction"] = time_it(lambda: kernels_lbfgs.direction(st.x, st.x_new, nl, st.qn, coef, 0, 1, cap))
    qred.begin()
    sec["reduce"] = time_it(lambda: qred.reduce(comm))
    dots_in = np.abs(np.arange(1.0, 2 * lb.m + 3))  # a positive g.g; the recursion's cost is that of any input

    def two_loop():
        mem = copy.deepcopy(lb)
        mem.direction(dots_in, 0.0, False)

    sec["two_loop"] = time_it(two_loop) - time_it(lambda: copy.deepcopy(lb))
    sec["lbfgs"] = sec["grad"] + sec["dots"] + sec["direction"] + sec["reduce"] + sec["two_loop"]
    sec["dual"] = sec["fire"] - sec["fire_nodual"]
    sec["pair_loop"] = sec["fire"] - sec["fire_norows"]
    fig_m = {}

    def metrics_pass():
        fig_m.update(measures.measure(solver, overlap_a=False)[0])

    sec["metrics"] = time_it(metrics_pass)
    fit_k = max(1, int(fit_steps))
    t_k = time_it(lambda: measures.best_kkt(solver, fig_m, 0.0, fit_k))
    t_0 = time_it(lambda: measures.best_kkt(solver, fig_m, 0.0, 0))
    sec["fit_step"] = (t_k - t_0) / fit_k
    hist = neighbors.history(nl, st.gid, st.pair_offsets, st.pair_j, st.pair_lambda)

    def build():
        offsets, pair_j, pair_lambda, _, mirror = neighbors.build_rows(
            st.x, nl, st.n_total, st.gid, st.diam, solver.skin, *hist)
        kernels_fire.pair_work(dim, nl, offsets, pair_j, pair_lambda, mirror)

    sec["build"] = time_it(build)
    sec["iteration"] = time_it(solver.step)
    bandwidth = comm.allreduce(np.array([triad_bandwidth(triad_n)]), op="min")[0]
    cached = comm.allreduce(np.array([triad_bandwidth(_TRIAD_CACHED_N, 20)]), op="min")[0]
    per_entry = totals[0] / n
    per_contact = totals[1] / n
    phases = {}
    for name, (seconds, cpu_seconds) in sec.items():
        ns = cpu_seconds * comm.size / n * 1e9
        row = {"seconds": seconds, "cpu_seconds": cpu_seconds, "ns_per_sphere": ns,
               "ns_per_sphere_wall": seconds * comm.size / n * 1e9}
        model = traffic_bytes(dim, lb.m).get(name)
        if model is not None:
            bps = model[0] + model[1] * per_entry + model[2] * per_contact
            row.update(bytes_per_sphere=bps, mb_per_s=bps / (ns * 1e-9) / 1e6 if ns > 0 else math.nan)
            row["bandwidth_fraction"] = row["mb_per_s"] * 1e6 / bandwidth
        phases[name] = row
    return {
        "dim": dim, "n": n, "ranks": comm.size, "seed": seed, "form": solver.scene.method.form,
        "state": {"iterations": int(res["iterations"]), "converged": bool(res["converged"]),
                  "stop_reason": str(res["stop_reason"]), "max_overlap": float(res["max_overlap"]),
                  "density": float(res["density"]), "run_seconds": run_seconds,
                  "lbfgs_phase": bool(s.qn), "c_b": float(cb)},
        "entries_per_sphere": float(per_entry), "contact_rows_per_sphere": float(per_contact),
        "lbfgs_memory": lb.m, "repeats": repeats,
        "triad_mb_per_s": float(bandwidth / 1e6), "triad_bytes": 24 * triad_n, "triad_cached_mb_per_s": float(cached / 1e6),
        "load_average": list(os.getloadavg()),
        "phases": phases,
    }


PHASE_ORDER = ("fire", "fire_nodual", "dual", "fire_norows", "pair_loop", "alm",
               "grad", "dots", "direction", "reduce", "two_loop", "lbfgs", "metrics", "fit_step", "build",
               "iteration")


def format_phases(r, lammps_ns=None):
    """The table of one ``phases_case`` result (lines); ``lammps_ns``: LAMMPS's FIRE step in ns
    per sphere on the same state, for the ratio and the target (at most half of it)."""
    st = r["state"]
    lines = [f"{r['dim']}D N = {r['n']}, {r['ranks']} rank(s): packed state after {st['iterations']} iterations "
             f"({st['stop_reason']}, converged {st['converged']}, max overlap {st['max_overlap']:.2e}, "
             f"density {st['density']:.4f}, {st['run_seconds']:.0f} s); {r['entries_per_sphere']:.1f} row "
             f"entries and {r['contact_rows_per_sphere']:.1f} contact rows per sphere; "
             f"triad {r['triad_mb_per_s']:.0f} MB/s ({r['triad_bytes'] / 2**20:.0f} MiB), "
             f"{r['triad_cached_mb_per_s']:.0f} MB/s (24 MiB); "
             f"load average {r['load_average'][0]:.1f}"]
    head = f"{'phase':<12} {'ns/sphere':>10} {'(wall)':>8} {'B/sphere':>9} {'MB/s':>8} {'of triad':>8}"
    if lammps_ns:
        head += f" {'x LAMMPS':>9} {'<= 1/2':>6}"
    lines.append(head)
    for name in PHASE_ORDER:
        p = r["phases"][name]
        line = f"{name:<12} {p['ns_per_sphere']:>10.1f} {p['ns_per_sphere_wall']:>8.1f}"
        if "bytes_per_sphere" in p:
            line += f" {p['bytes_per_sphere']:>9.0f} {p['mb_per_s']:>8.0f} {p['bandwidth_fraction']:>8.2f}"
        else:
            line += f" {'':>9} {'':>8} {'':>8}"
        if lammps_ns:
            ratio = p["ns_per_sphere"] / lammps_ns
            line += f" {ratio:>9.2f} {'yes' if ratio <= 0.5 else 'no':>6}"
        lines.append(line)
    if lammps_ns:
        lines.append(f"LAMMPS FIRE step on the same state: {lammps_ns:.1f} ns/sphere-step")
    return lines


def _lammps_ns(path, dim, n):
    """ns per sphere-step of tools/peers/lammps_fire.py results (JSON lines) of the same case,
    by rank 0's CPU clock (as ``ns_per_sphere``), the median over the lines of that case; None
    without one."""
    if path is None:
        return None
    found = []
    with open(path) as f:
        for line in f:
            if line.strip():
                got = json.loads(line)
                if got.get("dim") == dim and got.get("n") == n:
                    found.append(got["cpu_seconds_rank0"] * got.get("ranks", 1) / (got["steps"] * n) * 1e9)
    return float(np.median(found)) if found else None


def phases_main(args, comm):
    """``mpipack bench --phases``: the table of each case (``--json FILE`` appends one JSON
    line per case; ``--json -`` prints them after the tables)."""
    dims = args.dim or [2, 3]
    if args.quick:
        default_n = {1: 300, 2: 300, 3: 300}
        run_iters, repeats, target, fit_steps = args.run_iters or 200, 2, 0.01, 3
        triad_n = _TRIAD_CACHED_N
    else:
        default_n = {1: 10000, 2: 20000, 3: 10000}
        run_iters, repeats, target, fit_steps = args.run_iters, args.repeats or 5, 0.3, 50
        triad_n = _TRIAD_N
    cases = [(d, int(v)) for d in dims for v in args.n] if args.n else [(d, default_n[d]) for d in dims]
    rows = []
    for dim, n in cases:
        out = f"{args.state_out}-{dim}d-n{n}.npz" if args.state_out else None
        r = phases_case(comm, dim, n, run_iters, repeats, target, fit_steps, out, triad_n=triad_n)
        lammps = _lammps_ns(args.lammps_json, dim, n)
        if lammps:
            r["lammps_ns_per_sphere_step"] = lammps
        rows.append(r)
        if comm.rank == 0:
            print("\n".join(format_phases(r, lammps)), flush=True)
            if out:
                print(f"packed state written to {out}", flush=True)
    if comm.rank == 0 and args.json:
        if args.json == "-":
            for r in rows:
                print(json.dumps(r), flush=True)
        else:
            with open(args.json, "a") as f:
                for r in rows:
                    f.write(json.dumps(r) + "\n")
    return 0
