"""The loop, and the solver that advances one rank's share of the cloud: DAHA, AHA, NAP, NAV.

One iteration of DAHA / AHA, n -> n+1 (every rank, in lock step):

    step        kernels: lambda^n = max(0, lambda^{n-1} + beta phi(X^n))       (2.10b)
                         X^{n+1} from X^n, X^{n-1}, lambda^n, Xbar^n            (2.10a)
    reduce      ONE allreduce of named fields: exact sum X^{n+1} (-> Xbar^{n+1}),
                ||X^{n+1}-X^n||^2, ||X^n||^2, active pairs; largest step, max overlap, load, wall
    rebuild     when particles may have moved more than skin/2 since the rows were built:
                exchange (migrate with pair history), balance when max/mean particles per
                rank > neighbor.rebalance, borders, pair rows
    or forward  ghost positions X^{n+1} from their owners
    hooks       whatever is due: progress, output, metrics (``hooks``)
    stop        ||X^{n+1} - X^n|| / ||X^n|| < eps   (4.3), max_iter, or a hook's request

NAP and NAV run the same step/reduce/forward cycle for each inner iteration, with the
constraints linearised about the outer iterate X^p (see ``Solver._outer_step``).

Every decision (stop, rebuild, rebalance, numerical failure, hook schedules) is taken from
reduced numbers, so all ranks take it on the same iteration. Sums are exact (``exactsum``), pair
sums run in partner-gid order and the initial data is a function of gid only: the trajectory
is bitwise the same on any number of ranks.

Stopping criterion (4.3) in math: with X^n in R^{bN},
    ||X^{n+1} - X^n||_2 / ||X^n||_2 < eps.
It is a relative change, not a distance to the optimum: it can fire while the configuration is
still creeping (slow modes), and it is not translation invariant.
"""

import math
import time

import numpy as np

from . import comm as comm_mod
from . import domain, exactsum, hooks as hooks_mod, init, kernels, metrics, neighbors
from .reduction import Reduction
from .state import BlockState, State, gather_rows
from .timers import (BALANCE, BORDERS, EXCHANGE, FORWARD, HOOKS, REDUCE, ROWS, STEP,
                     PhaseTimers, format_report)


class NumericalError(RuntimeError):
    """NaN, Inf or divergence in the state."""


class TooDenseError(RuntimeError):
    """The pair rows of the current configuration would not fit in memory."""


# bytes per pair-row entry at the peak of a build (entry 12 B, growth copies, temporaries)
_BYTES_PER_ENTRY_PEAK = 40


def _available_memory_bytes():
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 2 ** 40


class Solver:
    """One rank's particles, ghosts and pair rows, and the decisions that advance them.
    ``scene`` is a ``config.Scene``, ``comm`` a ``comm.Comm``."""

    def __init__(self, scene, comm, timers=None):
        self.scene, self.comm = scene, comm
        self.dim, self.n = scene.dim, scene.n
        m = self.params = scene.method
        self.nested = m.nested
        self.beta = float(m.beta)
        if self.nested:
            self.coeffs = kernels.nested_coefficients(m.name, m.alpha, m.tau)
            self._kernel = kernels.nested_step(m.name, m.form)
        else:
            self.coeffs = kernels.coefficients(m.name, m.alpha, m.beta, m.gamma, m.c)
            self._kernel = kernels.multipliers_and_step(m.form, self.dim)
        self._metrics_kernel = kernels.pair_metrics(m.form)
        self.d_max = scene.particles.d_max
        self.skin = float(scene.neighbor.skin) * self.d_max
        self.r_ghost = self.d_max + self.skin
        self.state = State(self.dim, self.n)
        self.partition = domain.Partition.whole_space(self.dim)
        self.plan = comm_mod.GhostPlan.empty()
        self.xbar = np.zeros(self.dim)
        self.counters = {"rebuilds": 0, "rebalances": 0, "far_ghosts": 0, "max_imbalance": 1.0,
                         "inner_iterations": 0}
        self.timers = timers or PhaseTimers()
        self.clock0 = time.perf_counter()  # the loop's wall clock origin (set by run)
        # the per-iteration reduction: the step kernel's block, the load, the loop's clock
        self.red = Reduction()
        self.red.add_exact("step", [("x", self.dim), ("dx2", 1), ("xx2", 1)])
        self.red.add_max("step", [("step2", 1), ("overlap", 1)])
        self.red.add_count("active")
        self.red.add_max("load", [("max_local", 1)], fill=lambda: self.state.n_local)
        self.red.add_max("wall", [("wall", 1)], fill=lambda: time.perf_counter() - self.clock0)
        self._disp_bound = 0.0  # upper bound of the displacement since the rows were built
        # pair-row budget of this rank: neighbor.max_pair_gib, or its share of the node's
        # available memory (under a batch system's memory limit, set the key)
        gib = scene.neighbor.max_pair_gib
        budget = gib * 2 ** 30 if gib is not None else _available_memory_bytes() / comm.ranks_per_node
        self._max_entries = int(budget / _BYTES_PER_ENTRY_PEAK)

    # ---- set-up ----------------------------------------------------------------------------
    def initialise(self, source=None):
        """Start from the scene's initial data (source None) or from a ``BlockState`` (this
        rank's gid block of a saved state, e.g. a checkpoint read on any number of ranks).
        Either way every rank begins with a block of gids, then partition, migrate, ghosts, rows.
        """
        r, P, N = self.comm.rank, self.comm.size, self.n
        st = self.state
        if source is None:
            gids = np.arange(N * r // P, N * (r + 1) // P, dtype=np.int64)
            x = init.positions(self.scene, gids)
            local = {"x": x, "x_prev": x.copy(), "gid": gids, "diam": init.scene_diameters(self.scene, gids)}
            if self.nested:
                local["x_lin"] = x.copy()
            hist = (np.zeros(gids.shape[0] + 1, np.int64), np.zeros(0, np.int64), np.zeros(0))
            st.lambda_fresh, st.iteration = True, 0
        else:
            local = {"x": source.x, "x_prev": source.x_prev, "gid": source.gids, "diam": source.diam}
            if self.nested:
                local["x_lin"] = source.x_lin
            hist = (source.hist_offsets(), source.hist_gid, source.hist_lambda)
            st.lambda_fresh, st.iteration = bool(source.lambda_fresh), int(source.iteration)
            self.counters.update(source.counters)
        ghost = {k: v[:0] for k, v in local.items() if k != "x_prev"}
        lam_fresh = st.lambda_fresh
        st.set_particles(local, ghost)
        st.lambda_fresh = lam_fresh
        self.rebuild(rebalance=True, hist=hist)
        self.xbar = self._centre_of_mass()
        # compile (or load from the cache) the step kernel now, so the loop's timing excludes it
        scratch = Reduction().add_exact("step", [("x", self.dim), ("dx2", 1), ("xx2", 1)]) \
            .add_max("step", [("step2", 1), ("overlap", 1)]).begin()
        self._kernel(st.x, st.x_prev, st.x_new, 0, st.diam, st.pair_offsets, st.pair_j,
                     st.pair_lambda, self.xbar, *self.coeffs, self.beta, False,
                     scratch.acc("step"), scratch.maxima("step"))

    def _centre_of_mass(self):
        st = self.state
        red = Reduction().add_exact("sums", [("x", self.dim), ("xx", 1)]).begin()
        kernels.local_sums(st.x, st.n_local, red.acc("sums"))
        return red.reduce(self.comm).values("x") / self.n

    # ---- one iteration ----------------------------------------------------------------------
    def step(self):
        """Advance one (outer) iteration; returns the reduced figures of this iteration."""
        if self.nested:
            return self._outer_step()
        st = self.state
        fig = self._advance(st.x_prev, self.xbar)  # (2.10b) then (2.10a)
        self.xbar = fig.pop("xbar")
        st.iteration += 1
        fig["iteration"] = st.iteration
        return fig

    def _advance(self, x_other, xbar):
        """One kernel pass and everything after it: the reduction, the numerical guard, the
        rotation X^{n-1}, X^n <- X^n, X^{n+1}, and fresh ghosts (forward or rebuild).

        x_other is X^{n-1} (DAHA/AHA) or X^p (NAP/NAV). Returns the figures, with "xbar" of
        the new positions.
        """
        st, red, t = self.state, self.red.begin(), self.timers
        n_active = self._kernel(st.x, x_other, st.x_new, st.n_local, st.diam, st.pair_offsets,
                                st.pair_j, st.pair_lambda, xbar, *self.coeffs, self.beta,
                                not st.lambda_fresh, red.acc("step"), red.maxima("step"))
        st.lambda_fresh = False
        t.lap(STEP)
        red.set_count("active", n_active)
        red.reduce(self.comm)
        if red.overflowed() or not red.all_maxima_finite():
            raise NumericalError(
                f"non-finite or diverging positions at iteration {st.iteration + 1} "
                f"(NaN/Inf, or |X|^2 beyond {exactsum.RANGE:.3g}); lower alpha/beta or raise c")
        dx2, xx2 = red.value("dx2"), red.value("xx2")
        max_step = math.sqrt(red.max("step2"))
        fig = {
            "xbar": red.values("x") / self.n,
            "relative_change": math.sqrt(dx2 / xx2) if xx2 > 0 else (0.0 if dx2 == 0 else math.inf),
            "change2": dx2,
            "max_overlap": red.max("overlap"),
            "active_pairs": red.count("active") // 2,
            "max_step": max_step,
            "max_local": int(red.max("max_local")),
            "wall": red.max("wall"),
        }
        fig["imbalance"] = fig["max_local"] * self.comm.size / self.n
        self.counters["max_imbalance"] = max(self.counters["max_imbalance"], fig["imbalance"])
        t.lap(REDUCE)
        st.rotate()
        self._refresh_ghosts(max_step)
        return fig

    def _refresh_ghosts(self, max_move):
        """After local positions moved by at most ``max_move`` (a reduced value): fresh ghosts,
        by forward, or by a rebuild if the pair rows may have gone stale.

        Pair rows stay valid while no particle has moved more than skin/2 since the build.
        The sum of the largest moves bounds that displacement (triangle inequality) without
        reading x_build every iteration; only when the bound trips is the exact displacement
        measured (one more allreduce), and the rows rebuilt if it really exceeds skin/2.
        """
        st = self.state
        self._disp_bound += max_move
        if self._disp_bound > 0.5 * self.skin:
            local = neighbors.max_displacement2(st.x, st.x_build, st.n_local)
            exact = math.sqrt(self.comm.allreduce(np.array([local]), op="max")[0])
            if exact > 0.5 * self.skin or not math.isfinite(exact):
                self.timers.lap(FORWARD)
                self.rebuild()
                return
            self._disp_bound = exact
        comm_mod.forward(self.comm, self.plan, st.x, st.n_local)
        self.timers.lap(FORWARD)

    def _outer_step(self):
        """One outer iteration p -> p+1 of NAP (2.16) or NAV (2.17).

        The constraints are linearised about X^p (kept in x_lin, ghosts included, and carried
        through rebuilds). Inner steps run until the inner criterion, (4.1) for NAP:
        ||X^{p,n+1} - X^{p,n}|| / ||X^{p,n}|| < eps_inner, (4.2) for NAV:
        ||V^{p,n+1} - V^{p,n}|| / ||X^p|| < eps_inner / tau, or l_inner steps. Then
        lambda^{p+1} from the last inner iterate, and the outer criterion (4.3) is measured.
        NAV's inner variable is Y = X^p + tau V; it starts from V^{p,0} = V^p, i.e.
        Y = X^p + (X^p - X^{p-1}) (V^0 = 0).
        """
        st, m = self.state, self.params
        n = st.n_local
        st.x_lin[:] = st.x  # X^p, ghosts are current
        nav = m.name == "nav"
        xbar_p = self.xbar.copy()
        if nav:
            red = Reduction().add_exact("sums", [("x", self.dim), ("xx", 1)]).begin()
            kernels.local_sums(st.x, n, red.acc("sums"))
            norm_p = math.sqrt(red.reduce(self.comm).value("xx"))  # ||X^p||, for (4.2)
            st.x[:n] = 2.0 * st.x_lin[:n] - st.x_prev[:n]
            # the warm start moves every particle by |X^p - X^{p-1}|: it counts for the rows
            jump2 = neighbors.max_displacement2(st.x, st.x_lin, n)
            self._refresh_ghosts(math.sqrt(self.comm.allreduce(np.array([jump2]), op="max")[0]))
        inner = 0
        fig = {}
        for inner in range(1, int(m.l_inner) + 1):
            fig = self._advance(st.x_lin, xbar_p if nav else self.xbar)
            self.xbar = fig.pop("xbar")
            if nav:
                rel_inner = math.sqrt(fig["change2"]) / norm_p if norm_p > 0 else 0.0
            else:
                rel_inner = fig["relative_change"]
            if rel_inner < m.eps_inner:
                break
        self.counters["inner_iterations"] += inner
        # (2.16b) / (2.17b) for the last inner iterate: lambda^{p+1}; positions are discarded
        scratch = Reduction().add_exact("step", [("x", self.dim), ("dx2", 1), ("xx2", 1)]) \
            .add_max("step", [("step2", 1), ("overlap", 1)]).begin()
        self._kernel(st.x, st.x_lin, st.x_new, st.n_local, st.diam, st.pair_offsets, st.pair_j,
                     st.pair_lambda, self.xbar, *self.coeffs, self.beta, not st.lambda_fresh,
                     scratch.acc("step"), scratch.maxima("step"))
        st.lambda_fresh = True
        # outer criterion (4.3): ||X^{p+1} - X^p|| / ||X^p||
        red = Reduction().add_exact("change", [("d2", 1), ("p2", 1)]).begin()
        kernels.change_sums(st.x, st.x_lin, st.n_local, red.acc("change"))
        red.reduce(self.comm)
        d2, p2 = red.value("d2"), red.value("p2")
        st.x_prev[:st.n_local] = st.x_lin[:st.n_local]  # X^{p}, for NAV's V^{p+1}
        st.iteration += 1
        fig["relative_change"] = math.sqrt(d2 / p2) if p2 > 0 else (0.0 if d2 == 0 else math.inf)
        fig["iteration"] = st.iteration
        fig["inner_iterations"] = inner
        return fig

    # ---- rebuild: exchange, (balance), borders, rows -----------------------------------------
    def rebuild(self, rebalance=False, hist=None):
        """Exchange (and rebalance), sort locals by cell, borders, pair rows. Collective.

        hist: the locals' pair history (offsets, partner gid, lambda); default: from the rows.
        """
        st, comm, t = self.state, self.comm, self.timers
        if hist is None:
            hist = neighbors.history(st.n_local, st.gid, st.pair_offsets, st.pair_j, st.pair_lambda)
        part = st.local_fields()
        if comm.size > 1:
            if rebalance:
                self._balance(part)
            part, hist = comm_mod.exchange(comm, self.partition.owners(part["x"], part["x"].shape[0]), part, hist)
            t.lap(EXCHANGE)
            # migration may have unbalanced the load: check now (one small allreduce, only at
            # rebuilds) rather than wait for the next rebuild, which may be far away
            n_here = part["x"].shape[0]
            max_local = comm.allreduce(np.array([n_here], dtype=np.int64), op="max")[0]
            if not rebalance and max_local * comm.size > self.scene.neighbor.rebalance * self.n:
                self._balance(part)
                part, hist = comm_mod.exchange(comm, self.partition.owners(part["x"], n_here), part, hist)
                t.lap(EXCHANGE)
        # local particles in cell order: neighbours sit close in memory for the step kernel
        perm = neighbors.spatial_order(part["x"], part["x"].shape[0], self.r_ghost)
        part = {k: v[perm] for k, v in part.items()}
        h_off, h_idx = gather_rows(hist[0], perm)
        hist = (h_off, hist[1][h_idx], hist[2][h_idx])
        t.lap(ROWS)
        ghost_keys = ("x", "gid", "diam") + (("x_lin",) if "x_lin" in part else ())
        if comm.size > 1:
            p = self.partition
            offsets, idx = domain.ghost_destinations(part["x"], part["x"].shape[0], comm.rank,
                                                     p.lo, p.hi, self.r_ghost)
            self.plan, ghost, n_far = comm_mod.borders(comm, offsets, idx,
                                                       {k: part[k] for k in ghost_keys}, hist[1])
            self.counters["far_ghosts"] += n_far
            t.lap(BORDERS)
        else:
            ghost = {k: part[k][:0] for k in ghost_keys}
        lam_fresh = st.lambda_fresh
        st.set_particles(part, ghost)
        st.lambda_fresh = lam_fresh
        st.pair_offsets, st.pair_j, st.pair_lambda, missing = neighbors.build_rows(
            st.x, st.n_local, st.n_total, st.gid, st.diam, self.skin, *hist,
            max_entries=self._max_entries)
        too_dense = comm.allreduce(np.array([1 if missing < 0 else 0]), op="max")[0]
        if too_dense:
            raise TooDenseError(
                f"the configuration is too dense for memory: the pair rows of {self.n} spheres "
                f"would need more than {self._max_entries * _BYTES_PER_ENTRY_PEAK / 2**30:.1f} GiB "
                f"on a rank; spread the start (raise init.sigma, now {self.scene.init.sigma:g}), "
                f"use init.kind = \"lattice\", or run on more nodes (limit: neighbor.max_pair_gib)")
        if missing:
            raise RuntimeError(f"internal error: {missing} pair partners with lambda > 0 are missing "
                               f"on rank {comm.rank} after the ghost exchange")
        st.x_build = st.x[: st.n_local].copy()
        self._disp_bound = 0.0
        self.counters["rebuilds"] += 1
        t.lap(ROWS)

    def _balance(self, part):
        self.partition = domain.rcb(self.comm, part["x"], part["x"].shape[0])
        self.counters["rebalances"] += 1
        self.timers.lap(BALANCE)

    # ---- measures, end of run, state out -----------------------------------------------------
    def measure(self, update_lambda=False):
        """One metrics pass (collective): max overlap, KKT residual, complementarity, W.

        With update_lambda, lambda is first brought up to date with X by (2.10b) (the end of a
        DAHA/AHA run). Returns the reduced figures and, per local particle, pressure
        mu_i = sum_j lambda_ij and active contacts (arrays of n_local rows).
        """
        st = self.state
        red = Reduction().add_exact("met", [("kkt2", 1), ("gw2", 1)]) \
            .add_max("met", [("overlap", 1), ("complementarity", 1), ("max_lambda", 1)]) \
            .add_count("active").begin()
        pressure = np.zeros(st.n_local)
        contacts = np.zeros(st.n_local, dtype=np.int32)
        n_active = self._metrics_kernel(st.x, st.n_local, st.diam, st.pair_offsets, st.pair_j,
                                        st.pair_lambda, self.xbar, self.beta, update_lambda,
                                        red.acc("met"), red.maxima("met"), pressure, contacts)
        if update_lambda:
            st.lambda_fresh = True
        red.set_count("active", n_active)
        red.reduce(self.comm)
        kkt2, gw2 = red.value("kkt2"), red.value("gw2")
        fig = {
            "max_overlap": red.max("overlap"),
            "W": 0.5 * gw2,
            "kkt_residual": math.sqrt(kkt2 / gw2) if gw2 > 0 else (0.0 if kkt2 == 0 else math.inf),
            "complementarity": red.max("complementarity"),
            "max_lambda": red.max("max_lambda"),
            "active_pairs": red.count("active") // 2,
            "radius_of_gyration": math.sqrt(gw2 / self.n),
        }
        return fig, pressure, contacts

    def finish(self):
        """Bring lambda up to date with the final X (2.10b) and return the final figures:
        max overlap, W, KKT residual, packing density about the centre of mass, active pairs."""
        # DAHA/AHA hold lambda^{n-1}: one (2.10b) pass makes it lambda^n; NAP/NAV end every
        # outer iteration with fresh multipliers
        fig, _, _ = self.measure(update_lambda=not self.state.lambda_fresh)
        r_gyr = fig.pop("radius_of_gyration")
        radius = r_gyr if r_gyr > 0 else self.d_max
        red = Reduction().add_exact("cover", [("cover", 1)]).begin()
        metrics.covered_measure(self.state.x, self.state.diam, self.state.n_local, self.xbar,
                                np.array([radius]), red.acc("cover"))
        fig["density"] = red.reduce(self.comm).value("cover") / metrics.ball_measure(self.dim, radius)
        fig["density_radius"] = float(radius)
        return fig

    def export_state(self):
        """This rank's ``BlockState`` (collective): the state by gid, free of the partition."""
        st = self.state
        part = st.local_fields()
        hist = neighbors.history(st.n_local, st.gid, st.pair_offsets, st.pair_j, st.pair_lambda)
        part, hist = comm_mod.to_gid_blocks(self.comm, self.n, part, hist)
        r, P, N = self.comm.rank, self.comm.size, self.n
        return BlockState(n_global=N, dim=self.dim, gid_lo=N * r // P, x=part["x"],
                          x_prev=part["x_prev"], diam=part["diam"], hist_count=np.diff(hist[0]),
                          hist_gid=hist[1], hist_lambda=hist[2], x_lin=part.get("x_lin"),
                          iteration=st.iteration, lambda_fresh=st.lambda_fresh,
                          counters=dict(self.counters))

    def gather(self, root=0):
        """All particles and lambda > 0 pairs on ``root``, in gid order (for tests and small N).

        Returns dict(gid, x, x_prev, diam, pairs_gid (k, 2) with gid_i < gid_j, pairs_lambda)
        on root, None elsewhere.
        """
        st = self.state
        n = st.n_local
        gi, gj, lam = st.local_pairs()
        keep = gi < gj
        got = comm_mod.gather_by_gid(self.comm, {
            "gid": st.gid[:n], "x": st.x[:n], "x_prev": st.x_prev[:n], "diam": st.diam[:n],
            "_ragged": {"pi": gi[keep], "pj": gj[keep], "pl": lam[keep]}}, root=root)
        if got is None:
            return None
        rg = got.pop("_ragged")
        po = np.lexsort((rg["pj"], rg["pi"]))
        got["pairs_gid"] = np.stack([rg["pi"][po], rg["pj"][po]], axis=1)
        got["pairs_lambda"] = rg["pl"][po]
        return got


# ---- the loop ---------------------------------------------------------------------------------
def run(scene, comm, hooks=(), source=None, solver=None, profile=False):
    """The one loop: iterate a scene until its stop rule, running hooks on their schedules.

    scene: a config.Scene (its ``stop`` section is the stop rule); hooks: ``hooks.Hook``s;
    source: a BlockState to start from instead of the scene's initial data; solver: continue
    an existing Solver (its physics stays; only the stop rule comes from ``scene``).
    Stops at (4.3) when stop.eps > 0, at stop.max_iter iterations, or when a hook returns
    hooks.STOP. Returns (solver, result dict); with ``profile`` the result has the phase table.
    """
    timers = solver.timers if solver is not None else PhaseTimers()
    t0 = time.perf_counter()
    if solver is None:
        solver = Solver(scene, comm, timers)
        solver.initialise(source)
    setup_seconds = time.perf_counter() - t0
    eps, max_iter = scene.stop.eps, scene.stop.max_iter
    ctx = hooks_mod.Context(solver)
    converged = False
    start_iter = solver.state.iteration
    start_inner = solver.counters["inner_iterations"]
    t_loop = solver.clock0 = time.perf_counter()
    timers.start()
    for h in hooks:
        if h.at_start:
            h(ctx)
    while solver.state.iteration < max_iter:
        fig = solver.step()
        ctx.iteration, ctx.figures, ctx.elapsed = fig["iteration"], fig, fig["wall"]
        stop = False
        for h in hooks:
            if h.due(ctx.iteration, ctx.elapsed) and h(ctx) == hooks_mod.STOP:
                stop, ctx.stop_reason = True, h.name
        timers.lap(HOOKS)
        if stop:
            break
        if eps > 0 and fig["relative_change"] < eps:
            converged = True
            ctx.stop_reason = "eps"
            break
    loop_seconds = time.perf_counter() - t_loop
    timers.stop()
    final = solver.finish()
    iters = solver.state.iteration - start_iter
    # work: particle-iterations of the kernel, inner ones for the nested methods
    inner = solver.counters["inner_iterations"] - start_inner
    work = solver.n * (inner if solver.nested else iters)
    result = {
        "iterations": solver.state.iteration,
        "converged": converged,
        "stop_reason": ctx.stop_reason or ("max_iter" if solver.state.iteration >= max_iter else None),
        "relative_change": ctx.figures.get("relative_change", math.nan),
        "setup_seconds": setup_seconds,
        "loop_seconds": loop_seconds,
        "particle_iterations_per_second": work / loop_seconds if loop_seconds > 0 else 0.0,
        **final,
        **solver.counters,
    }
    if profile:
        result["profile"] = timers.report(comm, loop_seconds)
    ctx.result = result
    for h in hooks:
        if h.at_end:
            h(ctx)
    return solver, result


def profile_lines(result):
    """The phase table of a run with profile=True, as text lines."""
    return format_report(result["profile"])
