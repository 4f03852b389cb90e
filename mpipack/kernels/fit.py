"""Numba kernels of the multiplier fit (``fit``): the best nonnegative multipliers of a
configuration, for the certificate's KKT residual. Serial array code: never imports MPI.

For positions X and the pairs in contact to a tolerance (gap (r - d_kl) / d_kl <= tol: the
active set of an approximate KKT point), the fit minimises over m >= 0

    f(m) = 1/2 sum_i |r_i|^2,    r_i = (X_i - Xbar) + sum_j m_ij grad_{X_i} phi_ij,

the squared KKT residual of (2.4) with multipliers m. Its gradient per pair kl is

    g_kl = df/dm_kl = grad_k phi_kl . r_k + grad_l phi_kl . r_l = grad_k phi_kl . (r_k - r_l)

(grad_l phi_kl = -grad_k phi_kl), and a projected gradient step is m <- max(0, m - s g)
(accelerated as in ``fit``). A container's walls (``kernels.walls``) add a multiplier m_iw per
sphere and wall in contact, with g_iw = grad_i phi_iw . r_i (local: a wall has no partner),
held in (n_local, n_walls) arrays beside the pair contacts.
Layout as in ``kernels``: particle i's pairs are entries pair_offsets[i] .. pair_offsets[i+1]
of pair_j (indices into x, ghosts included), and every pair is stored in both partners' rows.
Each operation on a pair is bitwise symmetric in its partners (x_k - x_l = -(x_l - x_k) and
r_k - r_l = -(r_l - r_k) exactly), so both copies of m_kl stay equal, on one rank or two, and
each row sums in partner-gid order: the fit is the same on any number of ranks.
"""

import numpy as np

from mpipack.jit import njit
from mpipack.parallel import exactsum
from mpipack.kernels.daha import (NONSMOOTH, SMOOTH, constraint, coordinates, entry_multiplier, separation,
                                  wall_multiplier)
from mpipack.kernels import walls as walls_mod
from mpipack.kernels import potential

# exact rows: sum_i |r_i|^2 and the restart test's sum over entries of g (m_next - m_prev)
# (every pair counted twice, in both of its rows)
FIT_R2, FIT_TURN = 0, 1
N_FIT_EXACT = 2
# maxima: the largest row sum_j |grad_i phi_ij|^2 (bounds ||J^T J|| by Gershgorin, with a 2)
FIT_ROW = 0
N_FIT_MAX = 1


@njit(cache=True, inline="always")
def _start(form, x, n_local, diam, pair_offsets, pair_j, pair_lambda, walls, wall_lambda, beta,
           lambda_mode, lam_scale, pen, lam_floor, contact_tol, m, active, wm, wactive):
    dim = x.shape[1]
    for i in range(n_local):
        x0, x1, x2 = coordinates(dim, x, i)
        for wall in range(walls.shape[0]):
            s, n0, n1, n2, curv = walls_mod.gap(dim, walls, wall, x0, x1, x2)
            phi, cw = walls_mod.wall_constraint(form == SMOOTH, diam[i], s)
            wactive[i, wall] = s <= 0.5 * diam[i] * (1.0 + contact_tol)
            lam = wall_multiplier(form, wall_lambda[i, wall], phi, s, diam[i], beta, lambda_mode, pen,
                                  lam_floor, contact_tol)
            wm[i, wall] = lam * lam_scale if wactive[i, wall] else 0.0
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            j = pair_j[e]
            r2 = 0.0
            for k in range(dim):
                r2 += (x[i, k] - x[j, k]) ** 2
            dij = 0.5 * (diam[i] + diam[j])
            phi, _ = constraint(form, dij, r2)
            active[e] = r2 <= (dij * (1.0 + contact_tol)) ** 2
            lam = entry_multiplier(form, pair_lambda[e], phi, r2, dij, beta, lambda_mode, pen,
                                   lam_floor, contact_tol)
            m[e] = lam * lam_scale if active[e] else 0.0


@njit(cache=True)
def start_s(x, n_local, diam, po, pj, pl, wa, wl, beta, mode, scale, pen, floor, tol, m, active, wm, wact):
    _start(SMOOTH, x, n_local, diam, po, pj, pl, wa, wl, beta, mode, scale, pen, floor, tol, m, active, wm, wact)


@njit(cache=True)
def start_ns(x, n_local, diam, po, pj, pl, wa, wl, beta, mode, scale, pen, floor, tol, m, active, wm, wact):
    _start(NONSMOOTH, x, n_local, diam, po, pj, pl, wa, wl, beta, mode, scale, pen, floor, tol, m, active, wm,
           wact)


@njit(cache=True, inline="always")
def _wall_grad(form, dim, x, i, walls, wall, di):
    """grad_{X_i} phi_iw = -c n_iw as three scalars (c = d_i (S) or 1 (NS))."""
    x0, x1, x2 = coordinates(dim, x, i)
    s, n0, n1, n2, curv = walls_mod.gap(dim, walls, wall, x0, x1, x2)
    cw = di if form == SMOOTH else 1.0
    return -cw * n0, -cw * n1, -cw * n2


@njit(cache=True)
def contacts(pair_offsets, n_local, active):
    """The active entries as rows of their own: (c_offsets (n_local+1,), c_src (n_contacts,)
    int64, the entries' positions in the pair rows), each row in its original order."""
    c_offsets = np.zeros(n_local + 1, dtype=np.int64)
    for i in range(n_local):
        count = 0
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            if active[e]:
                count += 1
        c_offsets[i + 1] = c_offsets[i] + count
    c_src = np.empty(c_offsets[n_local], dtype=np.int64)
    c = 0
    for i in range(n_local):
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            if active[e]:
                c_src[c] = e
                c += 1
    return c_offsets, c_src


@njit(cache=True, inline="always")
def _grad(form, dim, x, xi0, xi1, xi2, j):
    """grad_{X_i} phi_ij as three scalars: -2 (X_i - X_j) (S) or -(X_i - X_j) / |X_i - X_j|
    (NS), X_i given as scalars; the coordinates beyond the dimension are 0."""
    g0, g1, g2, r2 = separation(dim, x, xi0, xi1, xi2, j)
    if form == SMOOTH:
        return -2.0 * g0, -2.0 * g1, -2.0 * g2
    r = np.sqrt(r2)
    if r > 0.0:
        return -g0 / r, -g1 / r, -g2 / r
    return 0.0, 0.0, 0.0


@njit(cache=True, inline="always")
def _fista(m, m_prev, g, step, beta):
    """One projected gradient step from y = m and FISTA's projected extrapolation: (new y,
    the step's m_next)."""
    new = m - step * g
    if new < 0.0:
        new = 0.0
    y = new + beta * (new - m_prev)
    if y < 0.0:
        y = 0.0
    return y, new


@njit(cache=True, inline="always")
def _step(form, dim, x, n_local, c_offsets, c_j, m, m_prev, g, walls, diam, wm, wm_prev, wg, wactive,
          xbar, pot, step, beta, r, acc):
    cols = exactsum.columns(acc)  # sum |r_i|^2, a block of spheres at a time
    xb0 = xbar[0]
    xb1 = xbar[1] if dim > 1 else 0.0
    xb2 = xbar[2] if dim > 2 else 0.0
    for i in range(n_local):
        xi0, xi1, xi2 = coordinates(dim, x, i)
        # grad W (``kernels.potential``): X_i - Xbar, or the sphere's weight under gravity
        r0, r1, r2_ = potential.pull(dim, pot, diam[i], xi0, xi1, xi2, xb0, xb1, xb2)
        for c in range(c_offsets[i], c_offsets[i + 1]):
            new = m[c] - step * g[c]  # the projected gradient step from the point y = m
            if new < 0.0:
                new = 0.0
            y = new + beta * (new - m_prev[c])  # the extrapolated point, projected
            if y < 0.0:
                y = 0.0
            m_prev[c] = new
            m[c] = y
            if y > 0.0:
                d0, d1, d2 = _grad(form, dim, x, xi0, xi1, xi2, np.uint64(c_j[c]))
                r0 += y * d0
                r1 += y * d1
                r2_ += y * d2
        for wall in range(walls.shape[0]):
            if not wactive[i, wall]:
                continue
            y, new = _fista(wm[i, wall], wm_prev[i, wall], wg[i, wall], step, beta)
            wm_prev[i, wall] = new
            wm[i, wall] = y
            if y > 0.0:
                d0, d1, d2 = _wall_grad(form, dim, x, i, walls, wall, diam[i])
                r0 += y * d0
                r1 += y * d1
                r2_ += y * d2
        r[i, 0] = r0
        rr = r0 * r0
        if dim > 1:
            r[i, 1] = r1
            rr += r1 * r1
        if dim > 2:
            r[i, 2] = r2_
            rr += r2_ * r2_
        exactsum.put(cols, FIT_R2, i, rr)
        if exactsum.block_ends(i):
            exactsum.add_block(cols, acc)
    exactsum.flush_columns(cols, acc, n_local)


@njit(cache=True, inline="always")
def _gradient(form, dim, x, n_local, c_offsets, c_j, m, m_prev, walls, diam, wm, wm_prev, wg, wactive,
              step, r, g, acc, maxima):
    cols = exactsum.columns(acc)  # the restart test's sum, a block of spheres at a time
    max_row = 0.0
    for i in range(n_local):
        turn = 0.0
        row = 0.0
        xi0, xi1, xi2 = coordinates(dim, x, i)
        ri0, ri1, ri2 = coordinates(dim, r, i)
        for c in range(c_offsets[i], c_offsets[i + 1]):
            j = np.uint64(c_j[c])
            d0, d1, d2 = _grad(form, dim, x, xi0, xi1, xi2, j)
            ge = d0 * (ri0 - r[j, 0])
            row += d0 * d0
            if dim > 1:
                ge += d1 * (ri1 - r[j, 1])
                row += d1 * d1
            if dim > 2:
                ge += d2 * (ri2 - r[j, 2])
                row += d2 * d2
            g[c] = ge
            # the restart test's g(y) . (m_next - m_prev), m_next the next step's projected
            # gradient step from y (the same expression as in _step, so the same bits)
            new = m[c] - step * ge
            if new < 0.0:
                new = 0.0
            turn += ge * (new - m_prev[c])
        for wall in range(walls.shape[0]):
            if not wactive[i, wall]:
                continue
            d0, d1, d2 = _wall_grad(form, dim, x, i, walls, wall, diam[i])
            ge = d0 * ri0 + d1 * ri1 + d2 * ri2
            row += d0 * d0 + d1 * d1 + d2 * d2
            wg[i, wall] = ge
            new = wm[i, wall] - step * ge
            if new < 0.0:
                new = 0.0
            turn += ge * (new - wm_prev[i, wall])
        if row > max_row:
            max_row = row
        exactsum.put(cols, FIT_TURN, i, turn)
        if exactsum.block_ends(i):
            exactsum.add_block(cols, acc)
    exactsum.flush_columns(cols, acc, n_local)
    maxima[FIT_ROW] = max_row


# One step and one gradient kernel per form and dimension (the dimension a compile-time constant:
# a sphere's coordinates in registers, LLVM's dead branches removed), written out because numba
# caches top-level functions only; error_model "numpy": no zero-division checks (the NS
# gradient's division is guarded).
@njit(cache=True, error_model="numpy")
def step_s1(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r, acc):
    _step(SMOOTH, 1, x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r,
          acc)


@njit(cache=True, error_model="numpy")
def gradient_s1(x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima):
    _gradient(SMOOTH, 1, x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima)


@njit(cache=True, error_model="numpy")
def step_s2(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r, acc):
    _step(SMOOTH, 2, x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r,
          acc)


@njit(cache=True, error_model="numpy")
def gradient_s2(x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima):
    _gradient(SMOOTH, 2, x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima)


@njit(cache=True, error_model="numpy")
def step_s3(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r, acc):
    _step(SMOOTH, 3, x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r,
          acc)


@njit(cache=True, error_model="numpy")
def gradient_s3(x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima):
    _gradient(SMOOTH, 3, x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima)


@njit(cache=True, error_model="numpy")
def step_ns1(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r, acc):
    _step(NONSMOOTH, 1, x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r,
          acc)


@njit(cache=True, error_model="numpy")
def gradient_ns1(x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima):
    _gradient(NONSMOOTH, 1, x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima)


@njit(cache=True, error_model="numpy")
def step_ns2(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r, acc):
    _step(NONSMOOTH, 2, x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r,
          acc)


@njit(cache=True, error_model="numpy")
def gradient_ns2(x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima):
    _gradient(NONSMOOTH, 2, x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima)


@njit(cache=True, error_model="numpy")
def step_ns3(x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r, acc):
    _step(NONSMOOTH, 3, x, n_local, co, cj, m, m_prev, g, wa, diam, wm, wm_prev, wg, wact, xbar, pot, step, beta, r,
          acc)


@njit(cache=True, error_model="numpy")
def gradient_ns3(x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima):
    _gradient(NONSMOOTH, 3, x, n_local, co, cj, m, m_prev, wa, diam, wm, wm_prev, wg, wact, step, r, g, acc, maxima)


_STEP = {("S", 1): step_s1, ("S", 2): step_s2, ("S", 3): step_s3,
         ("NS", 1): step_ns1, ("NS", 2): step_ns2, ("NS", 3): step_ns3}
_GRADIENT = {("S", 1): gradient_s1, ("S", 2): gradient_s2, ("S", 3): gradient_s3,
             ("NS", 1): gradient_ns1, ("NS", 2): gradient_ns2, ("NS", 3): gradient_ns3}
_START = {"S": start_s, "NS": start_ns}


def _by_dimension(kernels, form):
    """The kernel of ``form`` for x's dimension (x the first argument)."""
    def call(x, *args):
        return kernels[form, x.shape[1]](x, *args)
    return call


def fit_kernels(form):
    """(start, step, gradient) for a form.

    start(x, n_local, diam, pair_offsets, pair_j, pair_lambda, walls, wall_lambda, beta,
          lambda_mode, lam_scale, pen, lam_floor, contact_tol, m, active, wm, wactive): m
          (n_entries,) the run's own multipliers (``kernels.entry_multiplier`` times lam_scale)
          on pairs in contact, 0 elsewhere; active (n_entries,) bool, the pair is in contact to
          contact_tol; wm float64 and wactive bool (n_local, n_walls), the same for the walls.
    The walls' arrays (walls, diam, wm, wm_prev, wg, wactive) follow m_prev (step) and m_prev
    (gradient): every operation of a pair contact applied to each wall contact of a sphere.
    step(x, n_local, c_offsets, c_j, m, m_prev, g, <walls>, xbar, pot, s, beta, r, acc): over the pairs in
          contact only (``contacts``: c_offsets (n_local+1,) their rows, c_j their partners,
          m, m_prev and g (n_contacts,) per contact), from the point y = m with its gradient
          g: the projected gradient step m_next = max(0, y - s g), then y <- max(0, m_next +
          beta (m_next - m_prev)) and m_prev <- m_next (FISTA's extrapolation, projected so
          that every point whose residual is summed is a feasible m >= 0); r (n_total, b) rows
          of the local particles at the new y; acc row FIT_R2 (sum |r_i|^2).
    gradient(x, n_local, c_offsets, c_j, m, m_prev, <walls>, s, r, g, acc, maxima):
          g (n_contacts,) at y = m from r with fresh ghost rows; acc row FIT_TURN (sum of
          g (max(0, m - s g) - m_prev): positive when the next step turns back, the restart
          test of O'Donoghue and Candes); maxima[FIT_ROW] the largest row
          sum_j |grad_i phi_ij|^2 over the local particles.
    """
    return _START[form], _by_dimension(_STEP, form), _by_dimension(_GRADIENT, form)
