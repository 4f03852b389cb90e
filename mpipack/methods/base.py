"""The interface every method implements: what one iteration does to a ``Solver``'s state.

The engine (``engine.solver``) owns the mechanics every method shares: the state, the ghost
refresh and rebuilds, the reductions, the loop. A method owns the rest:

    its kernels          the numba step for its scheme, form and dimension (``kernels``)
    its coefficients     a typed NamedTuple, set per pass (``coefficients``)
    its state            ``save()`` / ``restore()``: what a checkpoint must carry to continue
                         bit for bit (JSON-able)
    its iteration        ``iterate(solver)``: one (outer) iteration, by the solver's collective
                         operations (``Solver.advance``, ``refresh_ghosts``, ``equalise``, ...)

Adding a method is adding one module with a subclass and a line in ``methods.for_scene``.
"""

from mpipack.kernels import daha as kernels


class Method:
    """One family of iterations. Subclasses set the attributes and override the methods below."""

    name = "method"
    #: the kernel's multipliers are updated with this beta when the metrics pass brings lambda
    #: up to date with X (``stop.measures``); a schedule may change it per phase
    beta = 0.0
    #: multipliers of the KKT system (2.4) per stored multiplier (NAV's solve (2.6): tau)
    kkt_lambda_scale = 1.0
    #: per-particle arrays beyond X^n and X^{n-1} that travel with a particle (NAP/NAV: x_lin)
    extra_fields = ()
    #: the watchdog's no-progress test applies (fixed-parameter schemes: a cycle or a wander)
    watch_stall = True
    #: the work of an iteration counts inner iterations (NAP/NAV)
    counts_inner = False
    #: the iterates do not depend on how far the pair rows reach beyond the contacts (entries
    #: with phi <= 0 and lambda = 0 add nothing), so the skin may change from build to build
    #: (``neighbor.adaptive_skin``); NAP/NAV's inner solves linearise every entry: False
    skin_free = True
    #: the adaptive skin's constant (``engine.rebuild.next_skin``); None: rebuild.SKIN_COST
    skin_cost = None

    #: W is gravity's (``kernels.potential``): the step kernel also sums W / g
    gravity = False

    def step_sums(self):
        """Exact fields the step kernel fills, in its row order: [(name, width)]."""
        return self.kernel_sums() + ([("wpot", 1)] if self.gravity else [])

    def kernel_sums(self):
        """The step kernel's own exact fields, before gravity's W / g (``step_sums``)."""
        return [("x", self.dim), ("dx2", 1), ("xx2", 1)]

    def step_maxima(self):
        """Maxima the step kernel fills, in its row order."""
        return [("step2", 1), ("overlap", 1)]

    def kernel_pass(self, solver, x_other, xbar, red, n_local=None, gradient_pass=False):
        """One pass of the step kernel over the first n_local particles (default all local)
        into ``red``'s step blocks; returns the number of row entries with lambda > 0."""
        raise NotImplementedError

    def step_figures(self, red, fig):
        """Add the method's own reduced figures of a pass to ``fig``."""

    def prepare(self, solver):
        """Compile (or load) the step kernel before the loop: one pass over no particle."""
        from mpipack.parallel.reduction import Reduction
        scratch = Reduction().add_exact("step", self.step_sums()) \
            .add_max("step", self.step_maxima()).begin()
        self.kernel_pass(solver, solver.state.x_prev, solver.xbar, scratch, n_local=0)

    def iterate(self, solver):
        """One (outer) iteration; returns its reduced figures (with "iteration")."""
        raise NotImplementedError

    def multipliers(self, lambda_fresh, finalize=False):
        """(lambda_mode, pen, lam_floor): which multipliers are those of the current X for the
        metrics pass (``stop.measures``): the stored ones when fresh, else (2.10b) applied on
        the fly (stored only with ``finalize``, at the end of a run)."""
        if lambda_fresh:
            return kernels.LAMBDA_STORED, 0.0, 0.0
        return (kernels.LAMBDA_UPDATE if finalize else kernels.LAMBDA_PEEK), 0.0, 0.0

    def advice(self):
        """A parameter change that would help an unstable or stalled run of this method."""
        return ""

    def save(self, solver):
        """The method's state for a checkpoint (JSON-able dict; merged into its ``extra``)."""
        return {}

    def restore(self, saved, solver):
        """Take back what ``save`` wrote (``saved`` is the checkpoint's whole ``extra``), after
        the solver has its particles, rows and centre of mass."""

    def summary(self):
        """What the run's summary says of the method (None: nothing)."""
        return None

    def work(self, iterations, inner_iterations):
        """Particle-iterations of the kernel per sphere: inner ones for the nested methods."""
        return inner_iterations if self.counts_inner else iterations


class PaperScheme(Method):
    """A method of the paper's with fixed coefficients (``self.coeffs``), dual gain ``self.beta``
    and a kernel ``self.kernel`` of the paper's signature (``kernels.daha``): the multiplier
    update (2.10b) when lambda is not yet the current X's, then the position update; it takes
    the container's walls (``kernels.walls``) and the potential (``kernels.potential``)."""

    def kernel_pass(self, solver, x_other, xbar, red, n_local=None, gradient_pass=False):
        st = solver.state
        n_local = st.n_local if n_local is None else n_local
        return self.kernel(st.x, x_other, st.x_new, n_local, st.diam, st.pair_offsets, st.pair_j,
                           st.pair_lambda, st.walls, st.wall_lambda, xbar, solver.pot, *self.coeffs,
                           self.beta, not st.lambda_fresh, red.acc("step"), red.maxima("step"))
