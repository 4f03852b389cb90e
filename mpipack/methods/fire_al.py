"""The fire-al method: DAHA's explosion, then FIRE on an augmented Lagrangian, then L-BFGS on
its stiff penalty, with parameters set every iteration from the reduced figures of the last
(``methods.fire_al_schedule`` decides; this object carries the decisions out on the state).

An iteration is either one pass of the fire-al kernel (``kernels.fire``) through
``Solver.advance``, or, once the schedule's penalty is stiff (``QN_FROM_CB``), an L-BFGS step
(``lbfgs_iteration``): the same kernel as a gradient pass, the memory's dots
(``kernels.lbfgs``) in the same ONE allreduce, the direction from the Gram matrix
(``methods.lbfgs``), then the per-sphere step before the ghosts are refreshed.
"""

import math

import numpy as np

from mpipack.kernels import daha as kernels
from mpipack.kernels import fire as kernels_fire
from mpipack.kernels import lbfgs as kernels_lbfgs
from mpipack.methods import lbfgs
from mpipack.methods.base import Method
from mpipack.kernels.potential import POT_G
from mpipack.methods.fire_al_schedule import FireALSchedule, Phase, Request, scene_law


class FireAL(Method):
    """The parameter-free schedule (``method.schedule = "fire-al"``), the default of DAHA
    scenes that set no parameters."""

    name = "fire-al"
    # FIRE's restarts and the augmented Lagrangian's dual steps make slow phases that the
    # watchdog's figures cannot tell from a cycle: the 3D N = 100 run of seed 1, which
    # certifies after 14750 iterations, would be stopped at 3250
    watch_stall = False

    def __init__(self, scene):
        self.dim, self.n = scene.dim, scene.n
        self.gravity = scene.potential.kind == "gravity"
        self.schedule = FireALSchedule(scene.n, scene.dim, scene.particles.d_mean,
                                       scene.method.form, overlap_tol=scene.stop.overlap,
                                       law=scene_law(scene), jammed=scene.stop.rule == "jammed")
        self.kernel = kernels_fire.fire_al_step(scene.method.form, scene.dim)
        # the adaptive skin's constant (``engine.rebuild.next_skin``): 2 (build cost) / (pass
        # cost per unit of skin), per sphere. The pass skips a shell entry in a few ns, and a 2D
        # sphere's shell holds fewer of them per unit of skin than a 3D one's: 25 in 2D (with the
        # ceiling config.SKIN_AUTO_FIRE_AL_2D: the skin ~0.7 d at the speed cap, rebuilds 2.2x
        # fewer, 2D N = 2000 and 2e4 jammed runs 5 - 12% sooner), 15 in 3D (ceiling
        # SKIN_AUTO_FIRE_AL_3D, rebuilds 1.8x fewer, certified runs 3 - 8% sooner);
        # rebuild.SKIN_COST in 1D
        self.skin_cost = {2: 25.0, 3: 15.0}.get(scene.dim)
        self.coeffs = FireALSchedule.NO_STEP
        self._lbfgs_reduction = None

    # ---- the kernel pass ---------------------------------------------------------------------
    def kernel_sums(self):
        return super().kernel_sums() + [("power", 1), ("force2", 1)]

    def step_maxima(self):
        return super().step_maxima() + [("max_gain", 1), ("max_row", 1)]

    def kernel_pass(self, solver, x_other, xbar, red, n_local=None, gradient_pass=False):
        """gradient_pass True (the kernel as L-BFGS's gradient pass, ``kernels.fire``): of the
        exact sums only |X^n|^2, no gain or row maxima, x_other not read."""
        st = solver.state
        n_local = st.n_local if n_local is None else n_local
        # the fire phase updates lambda every pass (its dual steps); the explosion is DAHA
        update = self.schedule.phase == Phase.FIRE or not st.lambda_fresh
        if n_local == 0:
            pairs = kernels_fire.WHOLE_ROWS
        else:
            if st.pair_work is None:  # the rows were built again
                st.pair_work = kernels_fire.pair_work(self.dim, st.n_local, st.pair_offsets, st.pair_j,
                                                      st.pair_lambda, st.pair_mirror)
                st.pair_mirror = None  # (the half list holds what the pass needs of it)
            pairs = st.pair_work
        return self.kernel(st.x, x_other, st.x_new, n_local, st.diam, st.pair_offsets, st.pair_j,
                           st.pair_lambda, pairs, st.walls, st.wall_lambda, xbar, solver.pot, *self.coeffs, update,
                           red.acc("step"),
                           red.maxima("step"), gradient_pass)

    def step_figures(self, red, fig):
        fig.update(power=red.value("power"), force2=red.value("force2"),
                   max_gain=red.max("max_gain"), max_row=red.max("max_row"))

    # ---- one iteration -----------------------------------------------------------------------
    def iterate(self, solver):
        st, sched = solver.state, self.schedule
        self._before(solver)
        if sched.quasi_newton_pass():
            fig = self.lbfgs_iteration(solver)
        else:
            fig = solver.advance(st.x_prev, solver.xbar)
        solver.end_iteration(fig)
        if sched.phase == Phase.FIRE:
            st.lambda_fresh = True  # lambda is the last dual step's (the certificate: measures)
        sched.observe(fig)
        return fig

    def _before(self, solver):
        """The schedule's requests, then the coefficients of the next pass."""
        st = solver.state
        for request in self.schedule.take_pending():
            if request == Request.EQUALISE:  # a dense start made a dilute uniform ball
                solver.equalise(self.schedule.spread_radius)
            elif request == Request.FILL:  # ... or spread over the room its container leaves
                solver.fill_container()
            elif request == Request.RESET_LAMBDA:
                st.pair_lambda[:] = 0.0
                st.wall_lambda[:] = 0.0
            elif request == Request.RESTART:  # momentum restart: X^{n-1} := X^n
                st.x_prev[:st.n_local] = st.x[:st.n_local]
        self.coeffs = self.schedule.coefficients()
        if self.schedule.phase != Phase.FIRE:
            self.beta = self.coeffs.beta  # the explosion's (2.10b), for a mid-run check

    def _lbfgs_red(self, solver):
        """The reduction of an L-BFGS iteration: the loop's blocks (``Solver.loop_reduction``)
        and the memory's (``kernels.lbfgs.dots``): the new gradient's dots with the 2m + 1
        slots and itself, the centre of mass of X^n, and the last step's |s|^2, slope g_old.s,
        max |s_i|^2 and shortened steps."""
        if self._lbfgs_reduction is None:
            k = lbfgs.slots(self.schedule.lbfgs.m)
            red = solver.loop_reduction()
            red.add_exact("qn", [("qn_dots", k + 1), ("qn_x", self.dim), ("qn_move2", 1),
                                 ("qn_slope", 1)])
            red.add_max("qn", [("qn_step2", 1)])
            red.add_count("qn_clipped")
            self._lbfgs_reduction = red
        return self._lbfgs_reduction

    def lbfgs_iteration(self, solver):
        """One L-BFGS iteration of the schedule's inner solve (``methods.lbfgs``,
        ``kernels.lbfgs``): the gradient g = grad L_rho at X^n (the fire-al kernel as a gradient
        pass), its dots with the memory, ONE reduction, the direction p = -H g from the Gram
        matrix (the same scalars on every rank), X^{n+1} = X^n + p (each sphere's move at most
        lbfgs.TRUST d).

        The gradient's grad W = X_i - Xbar uses the centre of mass of the previous iterate
        (this one's is reduced with the gradient): every step is a combination of gradients,
        whose sum over the spheres is N (Xbar^n - Xbar^{n-1}), so that the centre of mass moves
        only by rounding and shortened steps. W is that of X^n with its own Xbar."""
        st, t = solver.state, solver.timers
        lb = self.schedule.lbfgs
        red = self._lbfgs_red(solver).begin()
        k, n = lbfgs.slots(lb.m), st.n_local
        if st.qn is None or st.qn.shape[1] != k:
            st.qn = np.zeros((n, k, self.dim))
        n_active = self.kernel_pass(solver, st.x, solver.xbar, red, gradient_pass=True)  # x_new = X^n - g
        cap = lbfgs.TRUST * self.schedule.d
        head = lb.s["head"] if lb.s["stepped"] else -1
        clipped = kernels_lbfgs.dots(st.x, st.x_new, n, st.qn, head, cap, red.acc("qn"), red.maxima("qn"))
        t.lap(t.STEP)
        red.set_count("active", n_active)
        red.set_count("qn_clipped", clipped)
        red.reduce(solver.comm)
        solver.check_finite(red)
        xbar = red.values("qn_x") / self.n
        xx2, move2 = red.value("xx2"), red.value("qn_move2")
        if solver.point is not None:  # W pulls to a fixed point; X^{n+1} is not summed here
            w_point = solver.point_potential(xx2, red.values("qn_x"))
            xbar, solver.sum_x = solver.point.copy(), None
        elif self.gravity:  # W = g sum m_i (h_i - h_0) of X^n, summed by the gradient pass
            w_point = solver.pot[POT_G] * red.value("wpot")
        dots = red.values("qn_dots")  # g.S_j, g.Y_j, g.G_OLD, g.g
        solver.moves.settle(math.sqrt(red.max("qn_step2")))
        fig = {
            "xbar": xbar,
            "W": 0.5 * (xx2 - self.n * float(xbar @ xbar)) if solver.point is None and not self.gravity
            else w_point,
            # the change of the last step (X^n - X^{n-1})
            "relative_change": math.sqrt(move2 / xx2) if xx2 > 0 else 0.0,
            "change2": move2,
            "max_step": math.sqrt(red.max("qn_step2")),
            "power": 0.0, "force2": float(dots[-1]),  # (a gradient pass has no gain or row)
        }
        solver.common_figures(red, fig)
        coef, y_slot, s_slot, _ = lb.direction(dots, red.value("qn_slope"), red.count("qn_clipped") > 0)
        t.lap(t.REDUCE)
        if coef is None:
            kernels_lbfgs.backtrack(st.x, st.x_new, n, st.qn, s_slot)
        else:
            kernels_lbfgs.direction(st.x, st.x_new, n, st.qn, coef, y_slot, s_slot, cap)
        st.rotate()
        st.lambda_fresh = False
        t.lap(t.STEP)
        solver.moves.assume(cap)
        solver.refresh_ghosts(0.0)
        return fig

    # ---- what the rest of the engine asks ----------------------------------------------------
    def multipliers(self, lambda_fresh, finalize=False):
        if self.schedule.phase == Phase.FIRE:
            # the augmented Lagrangian's multipliers: the forces the next pass applies
            return (kernels.LAMBDA_FORCE, *self.schedule.force_multiplier())
        return super().multipliers(lambda_fresh, finalize)

    def advice(self):
        return ("the fire-al schedule should not do this: please report the scene and seed; "
                "meanwhile try another seed or method.form")

    def save(self, solver):
        out = {"schedule": self.schedule.save()}
        if self.schedule.s.qn:  # an L-BFGS pass does not recompute the next pass's Xbar
            out["qn_xbar"] = solver.xbar.tolist()
        return out

    def restore(self, saved, solver):
        if "schedule" in saved:
            self.schedule.restore(saved["schedule"])
        if "qn_xbar" in saved:
            # the L-BFGS pass uses the previous iterate's centre of mass (``lbfgs_iteration``)
            solver.xbar = np.array(saved["qn_xbar"], dtype=np.float64)

    def summary(self):
        return self.schedule.summary()
