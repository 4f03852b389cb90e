"""Numba kernels of the multiplier fit (``fit``): the best nonnegative multipliers of a
configuration, for the certificate's KKT residual. Serial array code: never imports MPI.

For positions X and the pairs in contact to a tolerance (gap (r - d_kl) / d_kl <= tol: the
active set of an approximate KKT point), the fit minimises over m >= 0

    f(m) = 1/2 sum_i |r_i|^2,    r_i = (X_i - Xbar) + sum_j m_ij grad_{X_i} phi_ij,

the squared KKT residual of (2.4) with multipliers m. Its gradient per pair kl is

    g_kl = df/dm_kl = grad_k phi_kl . r_k + grad_l phi_kl . r_l = grad_k phi_kl . (r_k - r_l)

(grad_l phi_kl = -grad_k phi_kl), and a projected gradient step is m <- max(0, m - s g)
(accelerated as in ``fit``).
Layout as in ``kernels``: particle i's pairs are entries pair_offsets[i] .. pair_offsets[i+1]
of pair_j (indices into x, ghosts included), and every pair is stored in both partners' rows.
Each operation on a pair is bitwise symmetric in its partners (x_k - x_l = -(x_l - x_k) and
r_k - r_l = -(r_l - r_k) exactly), so both copies of m_kl stay equal, on one rank or two, and
each row sums in partner-gid order: the fit is the same on any number of ranks.
"""

import numpy as np
from numba import njit

from . import exactsum
from .kernels import NONSMOOTH, SMOOTH, entry_multiplier

# exact rows: sum_i |r_i|^2 and the restart test's sum over entries of g (m_next - m_prev)
# (every pair counted twice, in both of its rows)
FIT_R2, FIT_TURN = 0, 1
N_FIT_EXACT = 2
# maxima: the largest row sum_j |grad_i phi_ij|^2 (bounds ||J^T J|| by Gershgorin, with a 2)
FIT_ROW = 0
N_FIT_MAX = 1


@njit(cache=True, inline="always")
def _grad(form, x, i, j, out):
    """grad_{X_i} phi_ij into out: -2 (X_i - X_j) (S) or -(X_i - X_j) / |X_i - X_j| (NS)."""
    dim = x.shape[1]
    r2 = 0.0
    for k in range(dim):
        out[k] = x[i, k] - x[j, k]
        r2 += out[k] * out[k]
    if form == SMOOTH:
        for k in range(dim):
            out[k] = -2.0 * out[k]
    else:
        r = np.sqrt(r2)
        for k in range(dim):
            out[k] = -out[k] / r if r > 0.0 else 0.0


@njit(cache=True, inline="always")
def _start(form, x, n_local, diam, pair_offsets, pair_j, pair_lambda, beta, lambda_mode,
           lam_scale, pen, lam_floor, contact_tol, m, active):
    dim = x.shape[1]
    for i in range(n_local):
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            j = pair_j[e]
            r2 = 0.0
            for k in range(dim):
                r2 += (x[i, k] - x[j, k]) ** 2
            dij = 0.5 * (diam[i] + diam[j])
            phi = dij * dij - r2 if form == SMOOTH else dij - np.sqrt(r2)
            active[e] = r2 <= (dij * (1.0 + contact_tol)) ** 2
            lam = entry_multiplier(form, pair_lambda[e], phi, r2, dij, beta, lambda_mode, pen,
                                   lam_floor, contact_tol)
            m[e] = lam * lam_scale if active[e] else 0.0


@njit(cache=True)
def start_s(x, n_local, diam, po, pj, pl, beta, mode, scale, pen, floor, tol, m, active):
    _start(SMOOTH, x, n_local, diam, po, pj, pl, beta, mode, scale, pen, floor, tol, m, active)


@njit(cache=True)
def start_ns(x, n_local, diam, po, pj, pl, beta, mode, scale, pen, floor, tol, m, active):
    _start(NONSMOOTH, x, n_local, diam, po, pj, pl, beta, mode, scale, pen, floor, tol, m, active)


@njit(cache=True, inline="always")
def _step(form, x, n_local, pair_offsets, pair_j, active, m, m_prev, g, xbar, step, beta, r, acc):
    dim = x.shape[1]
    fbuf = exactsum.staging(acc)
    grad = np.zeros(dim)
    for i in range(n_local):
        for k in range(dim):
            r[i, k] = x[i, k] - xbar[k]
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            if not active[e]:
                continue
            new = m[e] - step * g[e]  # the projected gradient step from the point y = m
            if new < 0.0:
                new = 0.0
            y = new + beta * (new - m_prev[e])  # the extrapolated point, projected
            if y < 0.0:
                y = 0.0
            m_prev[e] = new
            m[e] = y
            if y > 0.0:
                _grad(form, x, i, pair_j[e], grad)
                for k in range(dim):
                    r[i, k] += y * grad[k]
        r2 = 0.0
        for k in range(dim):
            r2 += r[i, k] * r[i, k]
        exactsum.add(fbuf, acc, FIT_R2, r2)
    exactsum.flush(fbuf, acc)


@njit(cache=True)
def step_s(x, n_local, po, pj, active, m, m_prev, g, xbar, step, beta, r, acc):
    _step(SMOOTH, x, n_local, po, pj, active, m, m_prev, g, xbar, step, beta, r, acc)


@njit(cache=True)
def step_ns(x, n_local, po, pj, active, m, m_prev, g, xbar, step, beta, r, acc):
    _step(NONSMOOTH, x, n_local, po, pj, active, m, m_prev, g, xbar, step, beta, r, acc)


@njit(cache=True, inline="always")
def _gradient(form, x, n_local, pair_offsets, pair_j, active, m, m_prev, step, r, g, acc, maxima):
    dim = x.shape[1]
    fbuf = exactsum.staging(acc)
    grad = np.zeros(dim)
    max_row = 0.0
    for i in range(n_local):
        turn = 0.0
        row = 0.0
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            if not active[e]:
                continue
            j = pair_j[e]
            _grad(form, x, i, j, grad)
            ge = 0.0
            for k in range(dim):
                ge += grad[k] * (r[i, k] - r[j, k])
                row += grad[k] * grad[k]
            g[e] = ge
            # the restart test's g(y) . (m_next - m_prev), m_next the next step's projected
            # gradient step from y (the same expression as in _step, so the same bits)
            new = m[e] - step * ge
            if new < 0.0:
                new = 0.0
            turn += ge * (new - m_prev[e])
        if row > max_row:
            max_row = row
        exactsum.add(fbuf, acc, FIT_TURN, turn)
    exactsum.flush(fbuf, acc)
    maxima[FIT_ROW] = max_row


@njit(cache=True)
def gradient_s(x, n_local, po, pj, active, m, m_prev, step, r, g, acc, maxima):
    _gradient(SMOOTH, x, n_local, po, pj, active, m, m_prev, step, r, g, acc, maxima)


@njit(cache=True)
def gradient_ns(x, n_local, po, pj, active, m, m_prev, step, r, g, acc, maxima):
    _gradient(NONSMOOTH, x, n_local, po, pj, active, m, m_prev, step, r, g, acc, maxima)


_KERNELS = {"S": (start_s, step_s, gradient_s), "NS": (start_ns, step_ns, gradient_ns)}


def fit_kernels(form):
    """(start, step, gradient) for a form.

    start(x, n_local, diam, pair_offsets, pair_j, pair_lambda, beta, lambda_mode, lam_scale,
          pen, lam_floor, contact_tol, m, active): m (n_entries,) the run's own multipliers
          (``kernels.entry_multiplier`` times lam_scale) on pairs in contact, 0 elsewhere;
          active (n_entries,) bool, the pair is in contact to contact_tol.
    step(x, n_local, pair_offsets, pair_j, active, m, m_prev, g, xbar, s, beta, r, acc):
          on active entries, from the point y = m with its gradient g: the projected
          gradient step m_next = max(0, y - s g), then y <- max(0, m_next + beta (m_next -
          m_prev)) and m_prev <- m_next (FISTA's extrapolation, projected so that every point
          whose residual is summed is a feasible m >= 0); r (n_total, b) rows of the local
          particles at the new y; acc row FIT_R2 (sum |r_i|^2).
    gradient(x, n_local, pair_offsets, pair_j, active, m, m_prev, s, r, g, acc, maxima):
          g (n_entries,) at y = m from r with fresh ghost rows; acc row FIT_TURN (sum of
          g (max(0, m - s g) - m_prev): positive when the next step turns back, the restart
          test of O'Donoghue and Candes); maxima[FIT_ROW] the largest row
          sum_j |grad_i phi_ij|^2 over the local particles.
    """
    return _KERNELS[form]
