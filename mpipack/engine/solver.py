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

Under the fire-al schedule (``method.schedule``, the default of DAHA scenes that set no
parameters) the step kernel is ``kernels_fire``'s, and ``schedule.FireAL`` sets its
coefficients before every pass from the previous iteration's reduced figures (``docs/
convergence.md``); the loop is the same. Once its penalty is stiff (``schedule.QN_FROM_CB``)
an iteration is an L-BFGS step (``_qn_advance``): the same kernel as a gradient pass, the
memory's dots (``kernels_qn``) in the same ONE allreduce, the direction from the Gram matrix
(``qn``), then the per-sphere step before the ghosts are refreshed.

NAP and NAV run the same step/reduce/forward cycle for each inner iteration, with the
constraints linearised about the outer iterate X^p (``nested.outer_step``). End-of-run
figures, the state by gid and gathers are in ``measures``.

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

from mpipack.parallel import comm as comm_mod
from mpipack.parallel import domain, exactsum, neighbors
from mpipack.engine import hooks as hooks_mod, initial as init
from mpipack.kernels import daha as kernels, lbfgs as kernels_qn
from mpipack.stop import measures
from mpipack.methods import nested
from mpipack.methods import lbfgs as qn
from mpipack.engine import rebuild as rebuild_mod
from mpipack.stop.certificate import Certifier
from mpipack.parallel.reduction import Reduction
from mpipack.parallel.state import State
from mpipack.engine.timers import (FORWARD, HOOKS, REDUCE, STEP, PhaseTimers, format_report, process_age_seconds)
from mpipack.stop import watchdog as watchdog_mod
from mpipack.stop.watchdog import Watchdog


class NumericalError(RuntimeError):
    """NaN, Inf, divergence or oscillation without progress (``watchdog``). ``solver`` holds
    the last good state: positions of the last finite iteration and their multipliers.
    ``kind``: "non-finite", "diverged" or "stalled"."""

    def __init__(self, message, solver, kind="diverged"):
        super().__init__(message)
        self.solver, self.kind = solver, kind


# set by a signal handler (``request_stop``), read into every reduction
_STOP_REQUEST = [0]


def request_stop(signum=1):
    """Ask the loop to stop (and the caller to checkpoint) at the end of the current iteration
    on every rank. Safe in a signal handler."""
    _STOP_REQUEST[0] = max(1, int(signum))


def stop_requested():
    return _STOP_REQUEST[0]


TooDenseError = rebuild_mod.TooDenseError


# resident bytes per particle, a conservative estimate of the arrays (X^n, X^{n-1}, X^{n+1}, at
# the last build; gid, diameter; about 6 (2D) / 12 (3D) pair entries with growth room) and of
# the set-up's temporaries; measured at a packed state: 160 (2D) and 262 (3D)
BYTES_PER_PARTICLE = {1: 250, 2: 400, 3: 650}
# a run diverges when its radius of gyration exceeds this multiple of its natural size
DIVERGENCE_FACTOR = 1e4


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
        self.beta = float(m.beta) if m.beta is not None else 0.0
        self.schedule = None  # the fire-al schedule, when the scene asks for it
        if self.nested:
            self.coeffs = kernels.nested_coefficients(m.name, m.alpha, m.tau)
            self._kernel = kernels.nested_step(m.name, m.form)
        elif m.schedule == "fire-al":
            from mpipack.kernels import fire as kernels_fire
            from mpipack.methods import fire_al as schedule
            self.schedule = schedule.FireAL(self.n, self.dim, init.mean_diameter(scene), m.form,
                                             overlap_tol=scene.stop.overlap)
            self._kernel = kernels_fire.fire_al_step(m.form, self.dim)
        else:
            self.coeffs = kernels.coefficients(m.name, m.alpha, m.beta, m.gamma, m.c)
            self._kernel = kernels.multipliers_and_step(m.form, self.dim)
        self._metrics_kernel = kernels.pair_metrics(m.form)
        # multipliers of the KKT system (2.4) per stored multiplier: NAV's solve (2.6)
        self.kkt_lambda_scale = float(m.tau) if m.name == "nav" else 1.0
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
        self.run_state = dict  # the loop's own state for a checkpoint (set by run)
        self.red = self._loop_reduction()
        self._disp_bound = 0.0  # upper bound of the displacement since the rows were built
        self._qn_cap_pending = 0.0  # an L-BFGS step's assumed move in the bound, until reduced
        self._red_qn = None
        # pair-row budget of this rank: neighbor.max_pair_gib, or its share of the node's
        # available memory (under a batch system's memory limit, set the key)
        gib = scene.neighbor.max_pair_gib
        budget = gib * 2 ** 30 if gib is not None else _available_memory_bytes() / comm.ranks_per_node
        self._max_entries = int(budget / rebuild_mod.BYTES_PER_ENTRY_PEAK)
        # refuse, before allocating anything, a system whose particle arrays alone cannot fit
        # (collective: nodes may differ in free memory)
        need = math.ceil(self.n / comm.size) * BYTES_PER_PARTICLE[self.dim]
        if comm.allreduce(np.array([1 if need > budget else 0]), op="max")[0]:
            raise TooDenseError(
                f"n = {self.n} spheres need about {need / 2**30:.3g} GiB per rank for the particle "
                f"arrays alone, more than the {budget / 2**30:.3g} GiB available per rank; use more "
                f"ranks or nodes, or fewer spheres (limit: neighbor.max_pair_gib)")
        self.r_diverge = math.inf  # radius of gyration beyond which the run diverges (initialise)

    def _loop_reduction(self):
        """The per-iteration reduction: the step kernel's blocks, the active pairs, the load,
        the loop's clock and a stop asked for by a signal on any rank (``request_stop``: all
        ranks see it together). An L-BFGS iteration adds its own blocks (``_qn_reduction``)."""
        red = Reduction()
        red.add_exact("step", self._step_sums())
        red.add_max("step", self._step_maxima())
        red.add_count("active")
        red.add_max("load", [("max_local", 1)], fill=lambda: self.state.n_local)
        red.add_max("wall", [("wall", 1)], fill=lambda: time.perf_counter() - self.clock0)
        red.add_max("stop_request", [("stop_request", 1)], fill=lambda: _STOP_REQUEST[0])
        return red

    def _step_sums(self):
        """Exact fields the step kernel fills (in its row order)."""
        fields = [("x", self.dim), ("dx2", 1), ("xx2", 1)]
        return fields + [("power", 1), ("force2", 1)] if self.schedule else fields

    def _step_maxima(self):
        fields = [("step2", 1), ("overlap", 1)]
        return fields + [("max_gain", 1), ("max_row", 1)] if self.schedule else fields

    def _kernel_pass(self, x_other, xbar, red, n_local=None, all_sums=True):
        """One pass of the step kernel over the local particles (the first ``n_local``) into
        ``red``'s step blocks; returns the number of row entries with lambda > 0. all_sums
        False (the fire-al kernel as L-BFGS's gradient pass): of the exact sums only |X^n|^2."""
        st = self.state
        n_local = st.n_local if n_local is None else n_local
        args = (st.x, x_other, st.x_new, n_local, st.diam, st.pair_offsets, st.pair_j,
                st.pair_lambda, xbar)
        if self.schedule is None:
            return self._kernel(*args, *self.coeffs, self.beta, not st.lambda_fresh,
                                red.acc("step"), red.maxima("step"))
        coeffs = self.sched_coeffs
        # the fire phase updates lambda every pass (its dual steps); the explosion is DAHA
        update = self.schedule.phase == "fire" or not st.lambda_fresh
        return self._kernel(*args, *coeffs, update, red.acc("step"), red.maxima("step"), all_sums)

    def advice(self):
        """A parameter change that would help an unstable or stalled run of this method."""
        m = self.params
        if self.schedule is not None:
            return ("the fire-al schedule should not do this: please report the scene and seed; "
                    "meanwhile try another seed or method.form")
        if m.name == "aha":
            return 'AHA has no damping: use method.name = "daha", or lower method.beta or method.alpha'
        if self.nested:
            return "lower method.alpha or method.tau, or raise method.l_inner"
        return ("`mpipack check SCENE` gives the stable range of the parameters (usually: raise method.c, "
                "lower method.beta or method.alpha); or leave method.alpha, beta, gamma and c unset for "
                "the fire-al schedule (docs/convergence.md)")

    def max_lambda(self):
        """max lambda_kl over all stored pairs (collective)."""
        st = self.state
        entries = int(st.pair_offsets[st.n_local])
        local = float(st.pair_lambda[:entries].max()) if entries > 0 else 0.0
        return float(self.comm.allreduce(np.array([local]), op="max")[0])

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
            if source.qn is not None:
                local["qn"] = source.qn
            hist = (source.hist_offsets(), source.hist_gid, source.hist_lambda)
            st.lambda_fresh, st.iteration = bool(source.lambda_fresh), int(source.iteration)
            self.counters.update(source.counters)
            if self.schedule is not None and "schedule" in source.extra:
                self.schedule.restore(source.extra["schedule"])
        ghost = {k: v[:0] for k, v in local.items() if k not in ("x_prev", "qn")}
        lam_fresh = st.lambda_fresh
        st.set_particles(local, ghost)
        st.lambda_fresh = lam_fresh
        self.rebuild(rebalance=True, hist=hist)
        self._break_coincidence()
        self.xbar, w0 = self._centre_of_mass()
        if source is not None and "qn_xbar" in source.extra:
            # the L-BFGS pass uses the previous iterate's centre of mass (``_qn_advance``)
            self.xbar = np.array(source.extra["qn_xbar"], dtype=np.float64)
        # natural size: the start's radius of gyration, or a packing's, whichever is larger
        r_start = math.sqrt(2.0 * max(w0, 0.0) / self.n)
        self.r_natural = max(r_start, self.d_max * self.n ** (1.0 / self.dim))
        self.r_diverge = DIVERGENCE_FACTOR * self.r_natural
        # compile (or load from the cache) the step kernel now, so the loop's timing excludes it
        scratch = Reduction().add_exact("step", self._step_sums()) \
            .add_max("step", self._step_maxima()).begin()
        if self.schedule is not None:
            self.sched_coeffs = self.schedule.NO_STEP
        self._kernel_pass(st.x_prev, self.xbar, scratch, n_local=0)
        # and the metrics pass, which every run needs at its end (and hooks may ask for sooner)
        measures.measure(self, empty=True)

    def _break_coincidence(self):
        """Spheres at exactly the same centre push each other nowhere: move them apart by a
        tiny displacement drawn from (seed, gid), collectively (``init.separate``)."""
        st = self.state
        flags = np.zeros(st.n_local, dtype=np.bool_)
        found = init.coincident_centres(st.x, st.n_local, st.pair_offsets, st.pair_j, flags)
        total = int(self.comm.allreduce(np.array([found], dtype=np.int64), op="sum")[0])
        if total == 0:
            return
        before = st.x[:st.n_local].copy()
        init.separate(self.scene.seed, st.gid[:st.n_local], st.x, st.x_prev, flags,
                      init.SEPARATION * self.d_max)
        if self.nested:  # the linearisation point moves with the particle
            st.x_lin[:st.n_local] += st.x[:st.n_local] - before
        self.counters["separated"] = total
        self.rebuild()

    def _equalise(self, radius):
        """Spread the cloud radially into a uniform ball of ``radius`` about Xbar, keeping
        directions and the order of radii (``init.equalise_radially``); collective: one max
        and one sum of integer counts, so the same on any rank count."""
        st, n = self.state, self.state.n_local
        local = float(((st.x[:n] - self.xbar) ** 2).sum(axis=1).max()) if n else 0.0
        r_max = math.sqrt(self.comm.allreduce(np.array([local]), op="max")[0])
        counts = self.comm.allreduce(init.radial_histogram(st.x, n, self.xbar, r_max), op="sum")
        init.equalise_radially(st.x, n, self.xbar, r_max, counts, radius, self.dim)
        self.rebuild()
        self.xbar, _ = self._centre_of_mass()

    def _centre_of_mass(self):
        """Xbar and W = 1/2 sum |X_i - Xbar|^2 of the current positions (collective)."""
        st = self.state
        red = Reduction().add_exact("sums", [("x", self.dim), ("xx", 1)]).begin()
        kernels.local_sums(st.x, st.n_local, red.acc("sums"))
        red.reduce(self.comm)
        xbar = red.values("x") / self.n
        return xbar, 0.5 * (red.value("xx") - self.n * float(xbar @ xbar))

    # ---- one iteration ----------------------------------------------------------------------
    def step(self):
        """Advance one (outer) iteration; returns the reduced figures of this iteration."""
        if self.nested:
            return nested.outer_step(self)
        st = self.state
        if self.schedule is not None:
            self._schedule_before()
        if self.schedule is not None and self.schedule.quasi_newton_pass():
            fig = self._qn_advance()
        else:
            fig = self._advance(st.x_prev, self.xbar)  # (2.10b) then (2.10a)
        self.xbar = fig.pop("xbar")
        st.iteration += 1
        fig["iteration"] = st.iteration
        if self.schedule is not None:
            if self.schedule.phase == "fire":
                st.lambda_fresh = True  # lambda is the last dual step's (the certificate: measures)
            self.schedule.observe(fig)
        return fig

    def _schedule_before(self):
        """The schedule's state changes and the coefficients of the next pass."""
        st = self.state
        for action in self.schedule.take_pending():
            if action == "equalise":  # a dense start made a dilute uniform ball
                self._equalise(self.schedule.spread_radius)
            elif action == "reset_lambda":
                st.pair_lambda[:] = 0.0
            elif action == "restart":  # momentum restart: X^{n-1} := X^n
                st.x_prev[:st.n_local] = st.x[:st.n_local]
        self.sched_coeffs = self.schedule.coefficients()
        if self.schedule.phase != "fire":
            self.beta = self.sched_coeffs[4]  # the explosion's (2.10b), for a mid-run check

    def _advance(self, x_other, xbar):
        """One kernel pass and everything after it: the reduction, the numerical guard, the
        rotation X^{n-1}, X^n <- X^n, X^{n+1}, and fresh ghosts (forward or rebuild).

        x_other is X^{n-1} (DAHA/AHA) or X^p (NAP/NAV). Returns the figures, with "xbar" of
        the new positions.
        """
        st, red, t = self.state, self.red.begin(), self.timers
        n_active = self._kernel_pass(x_other, xbar, red)
        st.lambda_fresh = True  # lambda^n, of X^n: the state stays consistent if we stop here
        t.lap(STEP)
        red.set_count("active", n_active)
        red.reduce(self.comm)
        self._check_finite(red)
        dx2, xx2 = red.value("dx2"), red.value("xx2")
        max_step = math.sqrt(red.max("step2"))
        fig = {
            "xbar": red.values("x") / self.n,
            # W^n = 1/2 sum |X_i^n - Xbar^n|^2 = 1/2 (sum |X_i^n|^2 - N |Xbar^n|^2): free here
            "W": 0.5 * (xx2 - self.n * float(xbar @ xbar)),
            "relative_change": math.sqrt(dx2 / xx2) if xx2 > 0 else (0.0 if dx2 == 0 else math.inf),
            "change2": dx2,
            "max_step": max_step,
        }
        if self.schedule is not None:
            fig.update(power=red.value("power"), force2=red.value("force2"),
                       max_gain=red.max("max_gain"), max_row=red.max("max_row"))
        self._common_figures(red, fig)
        t.lap(REDUCE)
        st.rotate()
        st.lambda_fresh = False  # X^{n+1} now; lambda^n is the previous one
        self._refresh_ghosts(max_step)
        return fig

    def _check_finite(self, red):
        """Numerical trouble in the reduced figures (NaN/Inf, an exact sum out of range)."""
        if red.overflowed() or not red.all_maxima_finite():
            raise NumericalError(
                f"non-finite or diverging positions at iteration {self.state.iteration + 1} "
                f"(NaN/Inf, or |X|^2 beyond {exactsum.RANGE:.3g}); {self.advice()}", self, "non-finite")

    def _common_figures(self, red, fig):
        """The figures every kind of iteration reports (max overlap, active pairs, load, wall,
        a stop request) into ``fig``, which holds W; raises if the cloud diverges."""
        fig.update(max_overlap=red.max("overlap"), active_pairs=red.count("active") // 2,
                   max_local=int(red.max("max_local")), wall=red.max("wall"))
        r_gyr = math.sqrt(2.0 * max(fig["W"], 0.0) / self.n)
        if r_gyr > self.r_diverge:
            raise NumericalError(
                f"the cloud diverges: radius of gyration {r_gyr:.3g} at iteration {self.state.iteration + 1}, "
                f"{DIVERGENCE_FACTOR:g} times its natural size; {self.advice()}", self)
        fig["imbalance"] = fig["max_local"] * self.comm.size / self.n
        self.counters["max_imbalance"] = max(self.counters["max_imbalance"], fig["imbalance"])
        fig["stop_request"] = red.max("stop_request") > 0

    def _qn_reduction(self):
        """The reduction of an L-BFGS iteration: the loop's blocks (``_loop_reduction``) and the
        memory's (``kernels_qn.dots``): the new gradient's dots with the 2m + 1 slots and
        itself, the centre of mass of X^n, and the last step's |s|^2, slope g_old.s, max
        |s_i|^2 and shortened steps."""
        if self._red_qn is None:
            k = qn.slots(self.schedule.lbfgs.m)
            red = self._loop_reduction()
            red.add_exact("qn", [("qn_dots", k + 1), ("qn_x", self.dim), ("qn_move2", 1),
                                 ("qn_slope", 1)])
            red.add_max("qn", [("qn_step2", 1)])
            red.add_count("qn_clipped")
            self._red_qn = red
        return self._red_qn

    def _qn_advance(self):
        """One L-BFGS iteration of the fire-al schedule's inner solve (``qn``, ``kernels_qn``):
        the gradient g = grad L_rho at X^n (the fire-al kernel as a gradient pass), its dots
        with the memory, ONE reduction, the direction p = -H g from the Gram matrix (the same
        scalars on every rank), X^{n+1} = X^n + p (each sphere's move at most qn.TRUST d).

        The gradient's grad W = X_i - Xbar uses the centre of mass of the previous iterate
        (this one's is reduced with the gradient): every step is a combination of gradients,
        whose sum over the spheres is N (Xbar^n - Xbar^{n-1}), so that the centre of mass moves
        only by rounding and shortened steps. W is that of X^n with its own Xbar."""
        st, t = self.state, self.timers
        sched, lb = self.schedule, self.schedule.lbfgs
        red = self._qn_reduction().begin()
        k, n = qn.slots(lb.m), st.n_local
        if st.qn is None or st.qn.shape[1] != k:
            st.qn = np.zeros((n, k, self.dim))
        n_active = self._kernel_pass(st.x_prev, self.xbar, red, all_sums=False)  # x_new = X^n - g
        cap = qn.TRUST * sched.d
        head = lb.s["head"] if lb.s["stepped"] else -1
        clipped = kernels_qn.dots(st.x, st.x_new, n, st.qn, head, cap, red.acc("qn"), red.maxima("qn"))
        t.lap(STEP)
        red.set_count("active", n_active)
        red.set_count("qn_clipped", clipped)
        red.reduce(self.comm)
        self._check_finite(red)
        xbar = red.values("qn_x") / self.n
        xx2, move2 = red.value("xx2"), red.value("qn_move2")
        dots = red.values("qn_dots")  # g.S_j, g.Y_j, g.G_OLD, g.g
        if self._qn_cap_pending > 0.0:  # the bound assumed a move of cap; now the real one
            self._disp_bound = max(0.0, self._disp_bound - self._qn_cap_pending
                                   + math.sqrt(red.max("qn_step2")))
        fig = {
            "xbar": xbar,
            "W": 0.5 * (xx2 - self.n * float(xbar @ xbar)),
            # the change of the last step (X^n - X^{n-1})
            "relative_change": math.sqrt(move2 / xx2) if xx2 > 0 else 0.0,
            "change2": move2,
            "max_step": math.sqrt(red.max("qn_step2")),
            "power": 0.0, "force2": float(dots[-1]),
            "max_gain": red.max("max_gain"), "max_row": red.max("max_row"),
        }
        self._common_figures(red, fig)
        coef, y_slot, s_slot, _ = lb.direction(dots, red.value("qn_slope"), red.count("qn_clipped") > 0)
        t.lap(REDUCE)
        if coef is None:
            kernels_qn.backtrack(st.x, st.x_new, n, st.qn, s_slot)
        else:
            kernels_qn.direction(st.x, st.x_new, n, st.qn, coef, y_slot, s_slot, cap)
        st.rotate()
        st.lambda_fresh = False
        t.lap(STEP)
        self._disp_bound += cap
        self._qn_cap_pending = cap
        self._refresh_ghosts(0.0)
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
            self._qn_cap_pending = 0.0  # the bound is now exact (or zero after the rebuild)
            if exact > 0.5 * self.skin or not math.isfinite(exact):
                self.timers.lap(FORWARD)
                self.rebuild()
                return
            self._disp_bound = exact
        if self.comm.size > 1:  # one rank has no ghosts to refresh
            comm_mod.forward(self.comm, self.plan, st.x, st.n_local)
        self.timers.lap(FORWARD)

    def rebuild(self, rebalance=False, hist=None):
        """Exchange (and rebalance), sort locals by cell, borders, pair rows (``rebuild``)."""
        rebuild_mod.rebuild(self, rebalance, hist)

    # ---- the state out (collective) -------------------------------------------------------
    def finish(self):
        """Final figures (``measures.finish``): lambda brought up to date with the final X."""
        return measures.finish(self)

    def export_state(self):
        """This rank's ``BlockState``: the state by gid, free of the partition."""
        return measures.export_state(self)

    def gather(self, root=0):
        """All particles and lambda > 0 pairs on ``root`` in gid order (tests, small N)."""
        return measures.gather(self, root)


# ---- the loop ---------------------------------------------------------------------------------
def run(scene, comm, hooks=(), source=None, solver=None, profile=False):
    """The one loop: iterate a scene until its stop rule, running hooks on their schedules.

    scene: a config.Scene (its ``stop`` section is the stop rule); hooks: ``hooks.Hook``s;
    source: a BlockState to start from instead of the scene's initial data; solver: continue
    an existing Solver (its physics stays; only the stop rule comes from ``scene``).
    Stops when the state is certified (stop.rule "certified", see ``certify``), or at (4.3)
    (rule "eps", when stop.eps > 0), at stop.max_iter iterations, or when a hook returns
    hooks.STOP. Returns (solver, result dict): "converged" is true only when the final state
    meets the certificate, "stop_reason" says what stopped the loop. With ``profile`` the
    result has the phase table.
    """
    timers = solver.timers if solver is not None else PhaseTimers()
    t0 = time.perf_counter()
    if solver is None:
        solver = Solver(scene, comm, timers)
        solver.initialise(source)
    setup_seconds = time.perf_counter() - t0
    stop_rule = scene.stop
    eps, max_iter = stop_rule.eps, stop_rule.max_iter
    certifier = Certifier(stop_rule)
    if source is not None and "certifier" in source.extra:
        certifier.restore(source.extra["certifier"])  # a restart: the same stop decisions
    watchdog = make_watchdog(solver, scene)
    if watchdog is not None and source is not None and "watchdog" in source.extra:
        watchdog.restore(source.extra["watchdog"])
    solver.run_state = lambda: {"certifier": certifier.save(),
                                **({"schedule": solver.schedule.save()} if solver.schedule else {}),
                                **({"watchdog": watchdog.save()} if watchdog else {}),
                                # an L-BFGS pass does not recompute the next pass's Xbar
                                **({"qn_xbar": solver.xbar.tolist()} if solver.schedule
                                   and solver.schedule.s["qn"] else {})}
    certified_rule = stop_rule.rule == "certified"
    ctx = hooks_mod.Context(solver)
    start_iter = solver.state.iteration
    start_inner = solver.counters["inner_iterations"]
    t_loop = solver.clock0 = time.perf_counter()
    timers.start()
    for h in hooks:
        if h.at_start:
            h(ctx)
    first_iteration = math.nan
    while solver.state.iteration < max_iter:
        fig = solver.step()
        if first_iteration != first_iteration:  # NaN until the first iteration is done
            first_iteration = process_age_seconds()
        ctx.iteration, ctx.figures, ctx.elapsed = fig["iteration"], fig, fig["wall"]
        stop = False
        for h in hooks:
            if h.due(ctx.iteration, ctx.elapsed) and h(ctx) == hooks_mod.STOP:
                stop, ctx.stop_reason = True, h.name
        certifier.record(ctx.iteration - 1, fig["W"])  # W^n comes with iteration n + 1
        if fig.get("stop_request") and not stop:
            stop, ctx.stop_reason = True, "signal"
        if stop_rule.max_seconds > 0 and fig["wall"] >= stop_rule.max_seconds and not stop:
            stop, ctx.stop_reason = True, "max_seconds"  # the wall clock is reduced: collective
        if ctx.iteration % stop_rule.check_every == 0 and not stop:
            if certifier.check(solver, fig) and certified_rule:
                stop, ctx.stop_reason = True, "certified"
        timers.lap(HOOKS)
        if stop:
            break
        if not certified_rule and eps > 0 and fig["relative_change"] < eps:
            ctx.stop_reason = "eps"
            break
        if watchdog is not None:
            watch(watchdog, solver, certifier, fig)
    loop_seconds = time.perf_counter() - t_loop
    timers.stop()
    final = solver.finish()
    certificate = certifier.final(solver, solver.state.iteration, final, ctx.stop_reason == "certified")
    # the KKT residual reported is the certificate's (the best multipliers' when they were
    # fitted); the run's own multipliers' beside it (the force imbalance is theirs)
    final["kkt_residual_run"] = final["kkt_residual"]
    final["kkt_residual"] = certificate["kkt"]["value"]
    iters = solver.state.iteration - start_iter
    # work: particle-iterations of the kernel, inner ones for the nested methods
    inner = solver.counters["inner_iterations"] - start_inner
    work = solver.n * (inner if solver.nested else iters)
    result = {
        "iterations": solver.state.iteration,
        # the packing meets every tolerance of the certificate (whatever stopped the loop)
        "converged": all(c["ok"] for c in certificate.values()),
        "certificate": certificate,
        # "certified", "eps" ((4.3) fired), "max_iter", or the name of the hook that stopped it
        "stop_reason": ctx.stop_reason or ("max_iter" if solver.state.iteration >= max_iter else None),
        "relative_change": ctx.figures.get("relative_change", math.nan),
        "setup_seconds": setup_seconds,
        "loop_seconds": loop_seconds,
        # from the start of the process (interpreter, imports, numba cache, set-up) to the
        # end of the first iteration of this loop
        "first_iteration_seconds": first_iteration,
        "particle_iterations_per_second": work / loop_seconds if loop_seconds > 0 else 0.0,
        **final,
        **solver.counters,
    }
    if solver.schedule is not None:
        result["schedule"] = solver.schedule.summary()
    if profile:
        result["profile"] = timers.report(comm, loop_seconds)
    ctx.result = result
    for h in hooks:
        if h.at_end:
            h(ctx)
    return solver, result


def make_watchdog(solver, scene):
    """The run's ``Watchdog`` (None with stop.watchdog = false). Its no-progress test is for
    the fixed-parameter schemes (the paper's methods as given), whose failure is a cycle or a
    wander; it is off under the fire-al schedule (FIRE's restarts and the augmented
    Lagrangian's dual steps make slow phases that its figures cannot tell from a cycle: the
    3D N = 100 run of seed 1, which certifies after 14750 iterations, would be stopped at
    3250) and when the scene asked for a fixed number of iterations (stop.rule "eps",
    stop.eps = 0)."""
    stop = scene.stop
    if not stop.watchdog:
        return None
    from mpipack.methods.fire_al import packing_law
    law = packing_law(solver.n, solver.dim, init.mean_diameter(scene), scene.method.form)
    return Watchdog(solver.n, solver.r_natural, law["lam_bar"] / solver.kkt_lambda_scale, stop.overlap,
                    stall=solver.schedule is None and not (stop.rule == "eps" and stop.eps == 0),
                    advice=solver.advice())


def watch(watchdog, solver, certifier, fig):
    """Feed the watchdog one iteration's figures; at a block's end, its verdict raised as a
    NumericalError (collective: every input is reduced)."""
    watchdog.observe(fig)
    it = fig["iteration"]
    if not watchdog.due(it):
        return
    last = certifier.last
    kkt = last["criteria"]["kkt"]["value"] if last and it - last["iteration"] < watchdog_mod.BLOCK else math.nan
    verdict = watchdog.block_end(it, solver.max_lambda(), certifier.w_change(it - 1, fig["W"]), kkt)
    if verdict is not None:
        kind, message = verdict
        raise NumericalError(message, solver, kind)


def profile_lines(result):
    """The phase table of a run with profile=True, as text lines."""
    return format_report(result["profile"])
