"""The certificate's KKT residual with the best multipliers: is there any lambda >= 0 on the
pairs in contact that balances the configuration? (collective)

A run's own multipliers (DAHA's lambda^n, the fire-al schedule's force multipliers) are an
estimate that lags the positions: the KKT residual they give is an upper bound of the
configuration's distance to stationarity. The residual of X itself is

    kkt(X) = min over m >= 0 of ||grad W(X) + sum_kl m_kl grad phi_kl(X)|| / ||grad W(X)||,

m on the pairs (and the walls, ``kernels.walls``) in contact to stop.overlap (the active set of an approximate KKT point, as for
the run's multipliers). It is what the certificate asks: X is stationary when some nonnegative
contact forces hold every sphere in balance. The fit starts from the run's multipliers and
takes projected gradient steps m <- max(0, y - g(y) / L) (``kernels_fit``, L the Gershgorin
bound of the Hessian) from points y extrapolated with FISTA's momentum (Beck and Teboulle),
projected onto m >= 0 and restarted whenever the next step would turn back (O'Donoghue and
Candes's gradient test); the residual reported is the least one met, each of an actual
m >= 0, so it is never below the true minimum.

Measured (docs/research/convergence.md, sections 3h and 3l): in a packed interior the run's multipliers are
off by the penalty's small overlaps and the fit removes nearly all of that imbalance within
30 - 100 steps (2D N = 32000: KKT 0.10 with the run's multipliers, 0.013 with the fit's,
all that remains on ~300 surface spheres with 2 - 3 contacts still settling). On a 3D N = 20000
packing (iterations 14250 and 15000 of the default run) the momentum halves the steps to a
given residual (from zero: 0.0126 and 0.0114 after 1000 steps, 0.0093 and 0.0083 after 2000,
against the spectral projected gradient's 0.0188, 0.0180, 0.0138, 0.0125), and that
configuration is itself within the certificate's 1e-2 from about iteration 14000: with this fit
(and fits that take the budget left, ``certify``) the run certifies at 14600 instead of 17500.

One fit step costs two passes over the pairs in contact (kept as rows of their own for the
fit), a ghost refresh of r and one fused allreduce: 134 us at 3D N = 2000 (1 rank), against
~390 us per iteration of the run's loop; every decision is taken from reduced values, so the
result is the same on every rank and on any number of ranks.
"""

import math

import numpy as np

from mpipack.parallel import comm as comm_mod
from mpipack.kernels import fit as kernels_fit
from mpipack.parallel.reduction import Reduction
from mpipack.stop.signals import Interrupted, stop_requested

MAX_STEPS = 2000  # the fit's steps at most
# ... and it stops once its least residual has not fallen by STALL_GAIN over STALL_STEPS steps
STALL_STEPS, STALL_GAIN = 300, 0.01


def best_kkt(s, mode, pen, lam_floor, gw2, target, max_steps=None):
    """The least KKT residual over multipliers m >= 0 on the pairs in contact to
    s.scene.stop.overlap, starting from the run's own (``kernels.entry_multiplier`` in
    ``mode``, with ``pen`` and ``lam_floor`` for the fire-al schedule's force multipliers).

    s: the ``Solver`` (positions with fresh ghosts, pair rows, xbar, pot); gw2 = ||grad W||^2
    (reduced: sum_i |X_i - Xbar|^2 for the centre); target: stop as soon as the residual is at most this;
    max_steps: at most this many steps (None: MAX_STEPS; never more). Returns (residual, steps
    taken). Changes nothing in the solver's state.
    """
    st, comm = s.state, s.comm
    n_local = st.n_local
    n_entries = int(st.pair_offsets[n_local])
    start, step, gradient = kernels_fit.fit_kernels(s.scene.method.form)
    m_rows = np.zeros(n_entries)
    active = np.zeros(n_entries, dtype=np.bool_)
    n_walls = st.walls.shape[0]
    wm = np.zeros((n_local, n_walls))  # the walls' multipliers, as m for the pair contacts
    wactive = np.zeros((n_local, n_walls), dtype=np.bool_)
    start(st.x, n_local, st.diam, st.pair_offsets, st.pair_j, st.pair_lambda, st.walls, st.wall_lambda,
          s.method.beta, mode, s.method.kkt_lambda_scale, pen, lam_floor, s.scene.stop.overlap, m_rows,
          active, wm, wactive)
    wm_prev, wg = np.zeros_like(wm), np.zeros_like(wm)
    walls = (st.walls, st.diam, wm, wm_prev, wg, wactive)
    # the pairs in contact, as rows of their own (the steps touch no other entry)
    c_offsets, c_src = kernels_fit.contacts(st.pair_offsets, n_local, active)
    c_j = st.pair_j[c_src]
    m = m_rows[c_src]  # the point y whose residual and gradient are evaluated
    m_prev = np.zeros_like(m)  # the last projected gradient step
    g = np.zeros_like(m)
    r = np.zeros((st.x.shape[0], s.dim))  # the residual per particle, ghost rows refreshed
    red = Reduction().add_exact("fit", [("r2", 1), ("turn", 1)]).add_max("fit", [("row", 1)]) \
        .add_max("stop", [("stop_request", 1)], fill=stop_requested)

    def one_step(length, beta):
        """The step from y = m (see ``kernels_fit``), then r and g at the new y and the
        restart test's sum (collective)."""
        red.begin()
        step(st.x, n_local, c_offsets, c_j, m, m_prev, g, *walls, s.xbar, s.pot, length, beta, r, red.acc("fit"))
        comm_mod.forward(comm, s.plan, r, n_local)
        gradient(st.x, n_local, c_offsets, c_j, m, m_prev, *walls, length, r, g, red.acc("fit"),
                 red.maxima("fit"))
        red.reduce(comm)
        if red.max("stop_request") > 0:  # a signal on some rank: every rank ends the fit here
            raise Interrupted("the multiplier fit was interrupted by a stop request")
        return red.value("r2")

    if not gw2 > 0:
        return math.inf, 0
    best = one_step(0.0, 0.0)  # the run's multipliers: r and g, no change (m_prev := m)
    lipschitz = 2.0 * red.max("row")
    if lipschitz <= 0:  # no pair in contact: the residual is that of W alone
        return math.sqrt(best / gw2), 0
    length = 1.0 / lipschitz
    target2 = target * target * gw2
    history = [best]  # the least residual after each step
    limit = MAX_STEPS if max_steps is None else min(max_steps, MAX_STEPS)
    steps, t, beta = 0, 1.0, 0.0
    while steps < limit and best > target2:
        # FISTA's momentum, restarted (t = 1) when the next step would turn back
        if red.value("turn") > 0.0:
            t, beta = 1.0, 0.0
        else:
            t_next = 0.5 * (1.0 + math.sqrt(1.0 + 4.0 * t * t))
            t, beta = t_next, (t - 1.0) / t_next
        r2 = one_step(length, beta)
        steps += 1
        best = min(best, r2)
        history.append(best)
        if steps >= STALL_STEPS and best > (1.0 - STALL_GAIN) ** 2 * history[-1 - STALL_STEPS]:
            break
    return math.sqrt(best / gw2), steps
