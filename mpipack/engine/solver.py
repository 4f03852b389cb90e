"""The ``Solver``: one rank's share of the cloud (particles, ghosts, pair rows) and the
collective operations every method iterates with. What an iteration computes is the method's
(``methods``); the loop that repeats it is ``engine.loop``.

One kernel pass and what follows it (``advance``), every rank in lock step:

    step        the method's kernel over the local particles: X^{n+1} (in x_new) from X^n,
                X^{n-1} (or X^p), lambda, Xbar, and the pass's exact sums and maxima
    reduce      ONE allreduce of named fields: exact sum X^{n+1} (-> Xbar^{n+1}),
                ||X^{n+1}-X^n||^2, ||X^n||^2, active pairs; largest step, max overlap, load,
                wall, a signal's stop request; the method's own fields beside them
    rotate      X^{n-1}, X^n <- X^n, X^{n+1}
    rebuild     when particles may have moved more than skin/2 since the rows were built:
                exchange (migrate with pair history), balance when max/mean particles per
                rank > neighbor.rebalance, borders, pair rows (``engine.rebuild``)
    or forward  ghost positions X^{n+1} from their owners

Every decision (stop, rebuild, rebalance, numerical failure) is taken from reduced numbers, so
all ranks take it on the same iteration. Sums are exact (``parallel.exactsum``), pair sums run
in partner-gid order and the initial data is a function of gid only: the trajectory is bitwise
the same on any number of ranks.
"""

import math
import time

import numpy as np

from mpipack.engine import initial as init
from mpipack.engine import memory
from mpipack.engine import rebuild as rebuild_mod
from mpipack.engine.timers import FORWARD, REDUCE, STEP, PhaseTimers
from mpipack.errors import NumericalError, TooDenseError
from mpipack.kernels import daha as kernels
from mpipack.kernels import potential, walls
from mpipack.methods import for_scene
from mpipack.parallel import comm as comm_mod
from mpipack.parallel import domain, exactsum, neighbors
from mpipack.parallel.reduction import Reduction
from mpipack.parallel.state import State
from mpipack.stop.signals import stop_requested

# a run diverges when its radius of gyration exceeds this multiple of its natural size
DIVERGENCE_FACTOR = 1e4


class MoveBound:
    """An upper bound of the displacement of any local sphere since the pair rows were built:
    the sum of the reduced largest moves (triangle inequality), so that x_build need not be
    read every iteration. An L-BFGS step is counted at its cap (``assume``) until its real
    largest move comes with the next reduction (``settle``)."""

    def __init__(self):
        self.bound = 0.0
        self.assumed = 0.0  # a step's assumed move in the bound, until reduced

    def reset(self):
        """The rows were just built: nothing has moved."""
        self.bound = self.assumed = 0.0

    def assume(self, cap):
        self.bound += cap
        self.assumed = cap

    def settle(self, real):
        """The last assumed move was in fact ``real``."""
        if self.assumed > 0.0:
            self.bound = max(0.0, self.bound - self.assumed + real)


class Solver:
    """One rank's particles, ghosts and pair rows, and the collective operations that advance
    them. ``scene`` is a ``config.Scene``, ``comm`` a ``parallel.comm.Comm``; ``method`` is
    the scene's (``methods.for_scene``)."""

    def __init__(self, scene, comm, timers=None):
        self.scene, self.comm = scene, comm
        self.dim, self.n = scene.dim, scene.n
        self.method = for_scene(scene)
        self.metrics_kernel = kernels.pair_metrics(scene.method.form)
        self.d_max = scene.particles.d_max
        # the Verlet skin: scene.neighbor.skin, or under neighbor.adaptive_skin chosen at each
        # build from the speed of the last period, at most that (``rebuild.next_skin``)
        self.skin_max = float(scene.neighbor.skin) * self.d_max
        self.adaptive_skin = bool(scene.neighbor.adaptive_skin) and self.method.skin_free
        self.set_skin(self.skin_max)
        self.usual_skin = True  # False while the rows are a dense start's (``initialise``)
        self.built_at = None  # the iteration of the last build (None: before the loop)
        self.rate = None  # the largest displacement per iteration over the last period
        self.state = State(self.dim, self.n)
        self.state.walls = walls.walls_of(scene.container, self.dim)
        self.pot = potential.parameters(scene)  # grad W per sphere (``kernels.potential``)
        self.gravity = scene.potential.kind == "gravity"
        self.grad_w2 = None  # gravity: |grad W|^2 = g^2 sum m_i^2, a constant (initialise)
        self.partition = domain.Partition.whole_space(self.dim)
        self.plan = comm_mod.GhostPlan.empty()
        self.xbar = np.zeros(self.dim)  # the point W pulls to: Xbar, or potential.point
        # potential.kind = "point": W = 1/2 sum |X_i - P|^2 needs sum X^n, which the pass that
        # moves X^n to X^{n+1} does not reduce: kept from the pass before (None: not known)
        self.point = (np.array(scene.potential.point, dtype=np.float64)
                      if scene.potential.kind == "point" else None)
        self.sum_x = None
        # skin_min, skin_max: the range of the builds' skins, in largest diameters
        self.counters = {"rebuilds": 0, "rebalances": 0, "far_ghosts": 0, "max_imbalance": 1.0,
                         "inner_iterations": 0, "skin_min": math.inf, "skin_max": 0.0}
        self.timers = timers or PhaseTimers()
        self.clock0 = time.perf_counter()  # the loop's wall clock origin (set by the loop)
        self.stop_rule = None  # the loop's (``stop.rule``): its state travels in checkpoints
        self.red = self.loop_reduction()
        self.moves = MoveBound()
        # pair-row budget of this rank; refuse, before allocating anything, a system whose
        # particle arrays alone cannot fit (collective: nodes may differ in free memory)
        budget = memory.rank_budget_bytes(scene, comm.ranks_per_node)
        self.max_pair_entries = int(budget / memory.BYTES_PER_ENTRY_PEAK)
        need = math.ceil(self.n / comm.size) * memory.BYTES_PER_PARTICLE[self.dim]
        if comm.allreduce(np.array([1 if need > budget else 0]), op="max")[0]:
            raise TooDenseError(
                f"n = {self.n} spheres need about {need / 2**30:.3g} GiB per rank for the particle "
                f"arrays alone, more than the {budget / 2**30:.3g} GiB available per rank; use more "
                f"ranks or nodes, or fewer spheres (limit: neighbor.max_pair_gib)")
        self.r_diverge = math.inf  # radius of gyration beyond which the run diverges (initialise)

    def loop_reduction(self):
        """The per-iteration reduction: the method's step blocks, the active pairs, the load,
        the loop's clock and a stop asked for by a signal on any rank (all ranks see it
        together). A method may extend it with blocks of its own."""
        red = Reduction()
        red.add_exact("step", self.method.step_sums())
        red.add_max("step", self.method.step_maxima())
        red.add_count("active")
        red.add_max("load", [("max_local", 1)], fill=lambda: self.state.n_local)
        red.add_max("wall", [("wall", 1)], fill=lambda: time.perf_counter() - self.clock0)
        red.add_max("stop_request", [("stop_request", 1)], fill=stop_requested)
        return red

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
        extra = self.method.extra_fields
        if source is None:
            gids = np.arange(N * r // P, N * (r + 1) // P, dtype=np.int64)
            diam = init.scene_diameters(self.scene, gids)
            x = init.contain(self.scene, init.positions(self.scene, gids), diam)
            local = {"x": x, "x_prev": x.copy(), "gid": gids, "diam": diam}
            local.update({name: x.copy() for name in extra})
            hist = (np.zeros(gids.shape[0] + 1, np.int64), np.zeros(0, np.int64), np.zeros(0))
            st.lambda_fresh, st.iteration = True, 0
        else:
            local = {"x": source.x, "x_prev": source.x_prev, "gid": source.gids, "diam": source.diam}
            local.update({name: getattr(source, name) for name in extra})
            if source.qn is not None:
                local["qn"] = source.qn
            if source.wall_lambda is not None:
                local["wall_lambda"] = source.wall_lambda
            hist = (source.hist_offsets(), source.hist_gid, source.hist_lambda)
            st.lambda_fresh, st.iteration = bool(source.lambda_fresh), int(source.iteration)
            self.counters.update(source.counters)
        ghost = {k: v[:0] for k, v in local.items() if k not in ("x_prev", "qn", "wall_lambda")}
        lam_fresh = st.lambda_fresh
        st.set_particles(local, ghost)
        st.lambda_fresh = lam_fresh
        # a dense fresh start's first rows take a small skin (init.DENSE_START_SKIN): its rows
        # are the run's largest (hundreds of entries a sphere, at the usual skin mostly pairs
        # beyond contact), and they last only until the spread (the first pass moves the
        # spheres by ~1e-3 d). A pair beyond contact adds exact zeros to every pass, so the
        # results are the same bits (for a method whose iterates do not depend on the rows'
        # reach, ``skin_free``); the next build takes the usual skin (``rebuild``)
        dense = source is None and self.method.skin_free and self._dense_start()
        self.rebuild(rebalance=True, hist=hist, skin=init.DENSE_START_SKIN * self.d_max if dense else None)
        self._break_coincidence()
        self.xbar, w0 = self.centre_of_mass()
        if source is not None:
            self.method.restore(source.extra, self)
        # natural size: the start's radius of gyration, or a packing's, whichever is larger
        r_start = math.sqrt(2.0 * max(w0, 0.0) / self.n)
        self.r_natural = max(r_start, self.d_max * self.n ** (1.0 / self.dim))
        self.r_diverge = DIVERGENCE_FACTOR * self.r_natural
        # compile (or load from the cache) the step kernel now, so the loop's timing excludes it
        self.method.prepare(self)
        # and the metrics pass, which every run needs at its end (and hooks may ask for sooner)
        from mpipack.stop import measures
        measures.measure(self, empty=True)

    def _dense_start(self):
        """Whether the start is dense (``initial.is_dense``: its spheres fill the uniform ball
        of their cloud's radius of gyration R_g, R^2 = (b+2)/b R_g^2, init.DENSE_START times
        over). Collective; plain float sums: it chooses the first build's skin, which changes
        no result."""
        st, b, n = self.state, self.dim, self.n
        x, d = st.x[:st.n_local], st.diam[:st.n_local]
        local = np.concatenate([x.sum(axis=0), [(x * x).sum(), ((0.5 * d) ** b).sum()]])
        total = self.comm.allreduce(local, op="sum")
        mean = total[:b] / n
        rg2 = total[b] / n - float(mean @ mean)
        return init.is_dense(n, b, total[b + 1], (b + 2) / b * rg2)

    def _break_coincidence(self):
        """Spheres at exactly the same centre push each other nowhere: move them apart by a
        tiny displacement drawn from (seed, gid), collectively (``initial.separate``)."""
        st = self.state
        flags = np.zeros(st.n_local, dtype=np.bool_)
        found = init.coincident_centres(st.x, st.n_local, st.pair_offsets, st.pair_j, flags)
        total = int(self.comm.allreduce(np.array([found], dtype=np.int64), op="sum")[0])
        if total == 0:
            return
        before = st.x[:st.n_local].copy()
        init.separate(self.scene.seed, st.gid[:st.n_local], st.x, st.x_prev, flags,
                      init.SEPARATION * self.d_max)
        for name in self.method.extra_fields:  # NAP/NAV's linearisation point moves with the particle
            getattr(st, name)[:st.n_local] += st.x[:st.n_local] - before
        self.counters["separated"] = total
        self.rebuild()

    def equalise(self, radius):
        """Spread the cloud radially into a uniform ball of ``radius`` about Xbar, keeping
        directions and the order of radii (``initial.equalise_radially``); collective: one max
        and one sum of integer counts, so the same on any rank count."""
        st, n = self.state, self.state.n_local
        local = float(((st.x[:n] - self.xbar) ** 2).sum(axis=1).max()) if n else 0.0
        r_max = math.sqrt(self.comm.allreduce(np.array([local]), op="max")[0])
        counts = self.comm.allreduce(init.radial_histogram(st.x, n, self.xbar, r_max), op="sum")
        init.equalise_radially(st.x, n, self.xbar, r_max, counts, radius, self.dim)
        self.rebuild()
        self.xbar, _ = self.centre_of_mass()

    def fill_container(self):
        """Spread the cloud uniformly over its container (``initial.fill_container``): each
        sphere to a place drawn from (seed, gid), inside by its radius; collective (a rebuild)."""
        st, n = self.state, self.state.n_local
        x = init.fill_container(self.scene, st.gid[:n], st.diam[:n])
        st.x[:n] = x
        st.x_prev[:n] = x
        self.rebuild()
        self.xbar, _ = self.centre_of_mass()

    def centre_of_mass(self):
        """Xbar and W = 1/2 sum |X_i - Xbar|^2 of the current positions (collective)."""
        st = self.state
        red = Reduction().add_exact("sums", [("x", self.dim), ("xx", 1)])
        if self.gravity:
            red.add_exact("gravity", [("wpot", 1), ("mm", 1)])
        red.begin()
        kernels.local_sums(st.x, st.n_local, red.acc("sums"))
        if self.gravity:
            potential.gravity_sums(st.x, st.diam, st.n_local, self.pot, red.acc("gravity"))
        red.reduce(self.comm)
        if self.gravity:  # W = g sum m_i (h_i - h_0); xbar (the centre of mass) is not pulled to
            g = self.pot[potential.POT_G]
            self.grad_w2 = g * g * red.value("mm")
            return red.values("x") / self.n, g * red.value("wpot")
        if self.point is not None:  # the point potential: P and W = 1/2 sum |X_i - P|^2
            self.sum_x = red.values("x")
            return self.point.copy(), self.point_potential(red.value("xx"), self.sum_x)
        xbar = red.values("x") / self.n
        return xbar, 0.5 * (red.value("xx") - self.n * float(xbar @ xbar))

    def point_potential(self, xx2, sum_x):
        """W = 1/2 sum_i |X_i - P|^2 = 1/2 (sum |X_i|^2 - 2 P.sum X_i + N |P|^2) from the exact
        sums xx2 = sum |X_i|^2 and sum_x = sum X_i (b,)."""
        p = self.point
        return 0.5 * (xx2 - 2.0 * float(p @ sum_x) + self.n * float(p @ p))

    # ---- one iteration ----------------------------------------------------------------------
    def step(self):
        """Advance one (outer) iteration of the method; returns its reduced figures."""
        return self.method.iterate(self)

    def end_iteration(self, fig):
        """After a one-pass iteration: Xbar^{n+1} taken from the figures, the count advanced."""
        self.xbar = fig.pop("xbar")
        self.state.iteration += 1
        fig["iteration"] = self.state.iteration
        return fig

    def advance(self, x_other, xbar):
        """One kernel pass of the method and everything after it: the reduction, the numerical
        guard, the rotation X^{n-1}, X^n <- X^n, X^{n+1}, and fresh ghosts (forward or rebuild).

        x_other is X^{n-1} (DAHA/AHA/fire-al) or X^p (NAP/NAV). Returns the figures, with
        "xbar" of the new positions.
        """
        st, red, t = self.state, self.red.begin(), self.timers
        n_active = self.method.kernel_pass(self, x_other, xbar, red)
        st.lambda_fresh = True  # lambda^n, of X^n: the state stays consistent if we stop here
        t.lap(STEP)
        red.set_count("active", n_active)
        red.reduce(self.comm)
        self.check_finite(red)
        dx2, xx2 = red.value("dx2"), red.value("xx2")
        max_step = math.sqrt(red.max("step2"))
        if self.gravity:  # W^n = g sum m_i (h_i^n - h_0), summed by the pass
            xbar_next, w = red.values("x") / self.n, self.pot[potential.POT_G] * red.value("wpot")
        elif self.point is None:
            xbar_next = red.values("x") / self.n
            # W^n = 1/2 sum |X_i^n - Xbar^n|^2 = 1/2 (sum |X_i^n|^2 - N |Xbar^n|^2): free here
            w = 0.5 * (xx2 - self.n * float(xbar @ xbar))
        else:
            if self.sum_x is None:  # X^n came from a pass that did not sum it (L-BFGS)
                self.centre_of_mass()
            xbar_next, w = self.point.copy(), self.point_potential(xx2, self.sum_x)
            self.sum_x = red.values("x")
        fig = {
            "xbar": xbar_next,
            "W": w,
            "relative_change": math.sqrt(dx2 / xx2) if xx2 > 0 else (0.0 if dx2 == 0 else math.inf),
            "change2": dx2,
            "max_step": max_step,
        }
        self.method.step_figures(red, fig)
        self.common_figures(red, fig)
        t.lap(REDUCE)
        st.rotate()
        st.lambda_fresh = False  # X^{n+1} now; lambda^n is the previous one
        self.refresh_ghosts(max_step)
        return fig

    def check_finite(self, red):
        """Numerical trouble in the reduced figures (NaN/Inf, an exact sum out of range)."""
        if red.overflowed() or not red.all_maxima_finite():
            raise NumericalError(
                f"non-finite or diverging positions at iteration {self.state.iteration + 1} "
                f"(NaN/Inf, or |X|^2 beyond {exactsum.RANGE:.3g}); {self.method.advice()}", self, "non-finite")

    def common_figures(self, red, fig):
        """The figures every kind of iteration reports (max overlap, active pairs, load, wall,
        a stop request) into ``fig``, which holds W; raises if the cloud diverges."""
        fig.update(max_overlap=red.max("overlap"), active_pairs=red.count("active") // 2,
                   max_local=int(red.max("max_local")), wall=red.max("wall"))
        if self.gravity:
            fig["grad_w2"] = self.grad_w2
        r_gyr = math.sqrt(2.0 * max(fig["W"], 0.0) / self.n)
        if r_gyr > self.r_diverge:
            raise NumericalError(
                f"the cloud diverges: radius of gyration {r_gyr:.3g} at iteration {self.state.iteration + 1}, "
                f"{DIVERGENCE_FACTOR:g} times its natural size; {self.method.advice()}", self)
        fig["imbalance"] = fig["max_local"] * self.comm.size / self.n
        self.counters["max_imbalance"] = max(self.counters["max_imbalance"], fig["imbalance"])
        fig["stop_request"] = red.max("stop_request") > 0

    def refresh_ghosts(self, max_move):
        """After local positions moved by at most ``max_move`` (a reduced value): fresh ghosts,
        by forward, or by a rebuild if the pair rows may have gone stale.

        Pair rows stay valid while no particle has moved more than skin/2 since the build.
        The bound (``MoveBound``) trips first; only then is the exact displacement measured
        (one more allreduce), and the rows rebuilt if it really exceeds skin/2.
        """
        st, moves = self.state, self.moves
        moves.bound += max_move
        if moves.bound > 0.5 * self.skin:
            local = neighbors.max_displacement2(st.x, st.x_build, st.n_local)
            with self.comm.charged_to("check"):  # (what the counts call it: parallel.comm)
                exact = math.sqrt(self.comm.allreduce(np.array([local]), op="max")[0])
            moves.assumed = 0.0  # the bound is now exact (or zero after the rebuild)
            if exact > 0.5 * self.skin or not math.isfinite(exact):
                if self.built_at is not None and math.isfinite(exact):
                    self.rate = exact / max(1, st.iteration + 1 - self.built_at)
                self.timers.lap(FORWARD)
                self.rebuild()
                return
            moves.bound = exact
        if self.comm.size > 1:  # one rank has no ghosts to refresh
            comm_mod.forward(self.comm, self.plan, st.x, st.n_local)
        self.timers.lap(FORWARD)

    def set_skin(self, skin):
        """The skin of the next build, and the ghost layer that goes with it."""
        self.skin = skin
        self.r_ghost = self.d_max + skin

    def rebuild(self, rebalance=False, hist=None, skin=None):
        """Exchange (and rebalance), sort locals by cell, borders, pair rows (``engine.rebuild``).
        Under an adaptive skin the build takes the skin that suits the last period's speed.
        ``skin``: this build's skin instead (a dense start's: not counted in the skin range;
        the build after it takes the usual skin)."""
        if skin is not None:
            self.usual_skin = False
            self.set_skin(skin)
        elif self.adaptive_skin and self.rate is not None:
            self.set_skin(rebuild_mod.next_skin(self.rate, self.d_max, self.skin_max,
                                                self.method.skin_cost))
            self.rate = None
        elif not self.usual_skin:  # the build after the start's
            self.set_skin(self.skin_max)
        with self.comm.charged_to("rebuild"):
            rebuild_mod.rebuild(self, rebalance, hist)
        self.moves.reset()
        self.built_at = self.state.iteration + 1
        if skin is None:
            self.usual_skin = True
            skin = self.skin / self.d_max
            self.counters["skin_min"] = min(self.counters["skin_min"], skin)
            self.counters["skin_max"] = max(self.counters["skin_max"], skin)

    # ---- the state out (collective) -------------------------------------------------------
    def finish(self):
        """Final figures (``stop.measures.finish``): lambda brought up to date with the final X."""
        from mpipack.stop import measures
        return measures.finish(self)

    def export_state(self):
        """This rank's ``BlockState``: the state by gid, free of the partition, with everything a
        continuation needs to take the same decisions (the method's and the stop rule's state)
        in its ``extra``: the one place a checkpoint's content is assembled."""
        from mpipack.stop import measures
        block = measures.export_state(self)
        block.extra = {**self.method.save(self), **(self.stop_rule.save() if self.stop_rule else {})}
        return block

    def gather(self, root=0):
        """All particles and lambda > 0 pairs on ``root`` in gid order (tests, small N)."""
        from mpipack.stop import measures
        return measures.gather(self, root)
