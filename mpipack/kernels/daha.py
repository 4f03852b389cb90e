"""Numba kernels of the damped Arrow-Hurwicz family. Serial array code: never imports MPI.

Notation (Degond, Ferreira, Motsch 2017). Positions X_i in R^b, diameters d_i,
d_kl = (d_k + d_l) / 2, and for every pair kl a multiplier lambda_kl >= 0. Constraint forms:

    NS (non-smooth):  phi_kl = d_kl - |X_k - X_l|,      grad_{X_k} phi_kl = -(X_k - X_l) / |X_k - X_l|
    S  (smooth):      phi_kl = d_kl^2 - |X_k - X_l|^2,  grad_{X_k} phi_kl = -2 (X_k - X_l)

Potential W = 1/(2N) sum_{i<j} |X_i - X_j|^2, so grad_{X_i} W = X_i - Xbar.

DAHA, gamma form (section 4.3; gamma = sqrt(alpha beta) is (2.10) exactly):

    (2.10b)  lambda_kl^n   = max(0, lambda_kl^{n-1} + beta phi_kl(X^n))
    (2.10a)  X_i^{n+1} = a1 X_i^n + a2 X_i^{n-1} - a3 (X_i^n - Xbar^n)
                         - sum_j lambda_ij^n (a3 + a4 phi_ij(X^n)) grad_{X_i} phi_ij(X^n)

with a1 = 2/(1+c/2), a2 = -(1-c/2)/(1+c/2), a3 = alpha^2/(1+c/2), a4 = gamma^2/(1+c/2).
AHA (2.8) is the same update with a1 = 1, a2 = 0, a3 = alpha, a4 = 0.

One pass over each particle's pair row does both equations: phi and its gradient at X^n serve
(2.10b) for lambda^n and then (2.10a) for X^{n+1}. The first iteration uses the given lambda^0
(update_lambda = False).

Data layout (see ``state.State``): rows i < n_local of ``x`` are local particles, the rest are
ghosts. Particle i's pairs are ``pair_j[pair_offsets[i]:pair_offsets[i+1]]`` (indices into x),
sorted by partner global id, with multipliers in ``pair_lambda`` at the same positions. Every
pair is stored in both partners' rows and updated identically in both, because phi is computed
from |X_k - X_l|^2, which is bitwise symmetric. Summing the row in partner-gid order makes the
result independent of how particles are distributed over ranks.
"""

import numpy as np

from mpipack.jit import njit
from mpipack.parallel import exactsum
from mpipack.kernels import metrics
from mpipack.kernels import walls as walls_mod
from mpipack.kernels import potential

SMOOTH = 0
NONSMOOTH = 1

# Layout of the per-rank statistics produced by one step.
# Exact sums (exactsum accumulator rows): sum X^{n+1} (b rows), sum |X^{n+1}-X^n|^2, sum |X^n|^2.
# Maxima (float64 >= 0): max |X^{n+1} - X^n|^2 (the step), max overlap (d_kl - r)/d_kl at X^n.
# Integer counts: number of row entries with lambda^n > 0 (each pair twice).
MAX_STEP2 = 0
MAX_OVERLAP = 1
N_MAX = 2


def coefficients(method, alpha, beta, gamma, c):
    """Scalar coefficients (a1, a2, a3, a4) of the position update for a method name."""
    if method == "daha":
        h = 1.0 + 0.5 * c
        return 2.0 / h, -(1.0 - 0.5 * c) / h, alpha * alpha / h, gamma * gamma / h
    if method == "aha":
        return 1.0, 0.0, alpha, 0.0
    raise ValueError(f"no one-pass kernel for method {method!r}")


@njit(cache=True, inline="always")
def coordinates(dim, x, i):
    """Row i of x as three scalars (0 beyond dim): a sphere's position held in registers."""
    return x[i, 0], x[i, 1] if dim > 1 else 0.0, x[i, 2] if dim > 2 else 0.0


@njit(cache=True, inline="always")
def separation(dim, x, xi0, xi1, xi2, j):
    """X_i - X_j as three scalars (0 beyond dim) and |X_i - X_j|^2, summed in coordinate order
    (the same bits for the pair in either row, up to the sign of the components); X_i is given
    as scalars, X_j is row j of x. Shared by every kernel that walks the pair rows."""
    d0 = xi0 - x[j, 0]
    d1 = 0.0
    d2 = 0.0
    r2 = d0 * d0
    if dim > 1:
        d1 = xi1 - x[j, 1]
        r2 += d1 * d1
    if dim > 2:
        d2 = xi2 - x[j, 2]
        r2 += d2 * d2
    return d0, d1, d2, r2


@njit(cache=True, inline="always")
def constraint(form, dij, r2):
    """The constraint of one pair (Definition 2.1) from its squared distance r2 = |X_i - X_j|^2:
    (phi_ij, r) with S phi = d_ij^2 - r^2 and NS phi = d_ij - r, r = |X_i - X_j| (NS only; 0.0
    in the smooth form, which needs no square root). Every kernel that walks the pair rows
    takes phi from here."""
    if form == SMOOTH:
        return dij * dij - r2, 0.0
    r = np.sqrt(r2)
    return dij - r, r


@njit(cache=True, inline="always")
def gradient_scale(form, m, r):
    """The factor s with m grad_{X_i} phi_ij = -s (X_i - X_j): S s = 2 m, NS s = m / r (0 for
    coincident centres, which have no direction)."""
    if form == SMOOTH:
        return 2.0 * m
    if r > 0.0:
        return m / r
    return 0.0


@njit(cache=True, inline="always")
def _multipliers_and_step(form, dim, x, x_prev, x_new, n_local, diam, pair_offsets, pair_j,
                          pair_lambda, walls, wall_lambda, xbar, pot, a1, a2, a3, a4, beta,
                          update_lambda, acc, maxima):
    # form and dim are compile-time constants of each wrapper below: LLVM removes the dead
    # branches and keeps the coordinates in registers (a runtime range(dim) loop does not).
    cols = exactsum.columns(acc)  # the per-sphere sums, summed a block of spheres at a time
    # c = 2 (and AHA) make the scheme one-step: a2 = 0, and X^{n-1} need not be read at all
    two_step = a2 != 0.0
    gravity = pot[potential.POT_KIND] == potential.GRAVITY
    xb0 = xbar[0]
    xb1 = xbar[1] if dim > 1 else 0.0
    xb2 = xbar[2] if dim > 2 else 0.0
    max_step2 = 0.0
    max_overlap = 0.0
    wall_overlap = 0.0
    min_ratio2 = 1.0
    n_active = 0
    for i in range(n_local):
        xi0, xi1, xi2 = coordinates(dim, x, i)
        f0 = 0.0
        f1 = 0.0
        f2 = 0.0
        di = diam[i]
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            j = pair_j[e]
            d0, d1, d2, r2 = separation(dim, x, xi0, xi1, xi2, j)
            dij = 0.5 * (di + diam[j])
            phi, r = constraint(form, dij, r2)
            lam = pair_lambda[e]
            if update_lambda:
                lam = lam + beta * phi
                if lam < 0.0:
                    lam = 0.0
                pair_lambda[e] = lam
            # largest overlap (d_ij - r)/d_ij, without a division per pair: track the
            # smallest r^2/d_ij^2 (S) or largest phi/d_ij (NS) by cross-multiplication
            if phi > 0.0:
                if form == SMOOTH:
                    if r2 < min_ratio2 * (dij * dij):
                        min_ratio2 = r2 / (dij * dij)
                elif phi > max_overlap * dij:
                    max_overlap = phi / dij
            if lam > 0.0:
                n_active += 1
                # lam (a3 + a4 phi) grad_i phi = -g (X_i - X_j)
                g = gradient_scale(form, lam * (a3 + a4 * phi), r)
                f0 -= g * d0
                f1 -= g * d1
                f2 -= g * d2
        # the container's walls: the same two equations per wall (``kernels.walls``), with
        # lambda_iw stored with the sphere; a contact counts twice, as a pair in both its rows
        for wall in range(walls.shape[0]):
            s, n0, n1, n2, curv = walls_mod.gap(dim, walls, wall, xi0, xi1, xi2)
            phi, cw = walls_mod.wall_constraint(form == SMOOTH, di, s)
            lam = wall_lambda[i, wall]
            if update_lambda:
                lam = lam + beta * phi
                if lam < 0.0:
                    lam = 0.0
                wall_lambda[i, wall] = lam
            if phi > 0.0 and (0.5 * di - s) > wall_overlap * (0.5 * di):
                wall_overlap = (0.5 * di - s) / (0.5 * di)
            if lam > 0.0:
                n_active += 2
                g = lam * (a3 + a4 * phi) * cw  # m grad_i phi_iw = -g n_iw
                f0 -= g * n0
                f1 -= g * n1
                f2 -= g * n2
        # grad W (``kernels.potential``): X_i - Xbar, or the sphere's weight under gravity
        p0, p1, p2 = potential.pull(dim, pot, di, xi0, xi1, xi2, xb0, xb1, xb2)
        if gravity:
            exactsum.put(cols, dim + 2, i, potential.height_energy(dim, pot, di, xi0, xi1, xi2))
        # (2.10a); also the exact partial sums and the maxima for the fused reduction
        xn0 = a1 * xi0 + (a2 * x_prev[i, 0] if two_step else 0.0) - a3 * p0 - f0
        x_new[i, 0] = xn0
        exactsum.put(cols, 0, i, xn0)
        dx2 = (xn0 - xi0) * (xn0 - xi0)
        xx2 = xi0 * xi0
        if dim > 1:
            xn1 = a1 * xi1 + (a2 * x_prev[i, 1] if two_step else 0.0) - a3 * p1 - f1
            x_new[i, 1] = xn1
            exactsum.put(cols, 1, i, xn1)
            dx2 += (xn1 - xi1) * (xn1 - xi1)
            xx2 += xi1 * xi1
        if dim > 2:
            xn2 = a1 * xi2 + (a2 * x_prev[i, 2] if two_step else 0.0) - a3 * p2 - f2
            x_new[i, 2] = xn2
            exactsum.put(cols, 2, i, xn2)
            dx2 += (xn2 - xi2) * (xn2 - xi2)
            xx2 += xi2 * xi2
        exactsum.put(cols, dim, i, dx2)
        exactsum.put(cols, dim + 1, i, xx2)
        if exactsum.block_ends(i):
            exactsum.add_block(cols, acc)
        if dx2 > max_step2 or dx2 != dx2:
            max_step2 = dx2
    exactsum.flush_columns(cols, acc, n_local)
    if form == SMOOTH:
        max_overlap = 1.0 - np.sqrt(min_ratio2)
    maxima[MAX_STEP2] = max_step2
    if wall_overlap > max_overlap:  # (a NaN max_overlap stays NaN: the guard must see it)
        max_overlap = wall_overlap
    maxima[MAX_OVERLAP] = max_overlap
    return n_active


_DOC = """(2.10b) then (2.10a) for one form and dimension; see the module docstring.

    Shapes: x, x_prev, x_new (n_total, b); diam (n_total,); pair_offsets (n_local+1,);
    pair_j int32 and pair_lambda float64 (n_pairs,); walls (n_walls, 8) and wall_lambda
    (n_local, n_walls) (``kernels.walls``; n_walls = 0 without a container); xbar (b,) and pot
    (4,) (``kernels.potential``: grad W);
    acc int64 (b+2, exactsum.NBINS+1), added to (b+3 under gravity: row b+2 sum m_i (h_i - h_0));
    maxima float64 (N_MAX,), overwritten. Writes x_new[:n_local] and, if update_lambda, pair_lambda and wall_lambda. Returns the
    number of row entries with lambda > 0 (a wall contact counts 2, like a pair's two entries).
    """


# One small wrapper per (form, dim), so that only what a scene uses is compiled (and cached).
# Written out rather than made by a closure factory: numba caches top-level functions only.
@njit(cache=True)
def step_s1(x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx):
    return _multipliers_and_step(SMOOTH, 1, x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx)


@njit(cache=True)
def step_s2(x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx):
    return _multipliers_and_step(SMOOTH, 2, x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx)


@njit(cache=True)
def step_s3(x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx):
    return _multipliers_and_step(SMOOTH, 3, x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx)


@njit(cache=True)
def step_ns1(x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx):
    return _multipliers_and_step(NONSMOOTH, 1, x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx)


@njit(cache=True)
def step_ns2(x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx):
    return _multipliers_and_step(NONSMOOTH, 2, x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx)


@njit(cache=True)
def step_ns3(x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx):
    return _multipliers_and_step(NONSMOOTH, 3, x, x_prev, x_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, a1, a2, a3, a4, beta, upd, acc, mx)


_STEPS = {("S", 1): step_s1, ("S", 2): step_s2, ("S", 3): step_s3,
          ("NS", 1): step_ns1, ("NS", 2): step_ns2, ("NS", 3): step_ns3}
for _f in _STEPS.values():
    _f.__doc__ = _DOC


def multipliers_and_step(form, dim):
    """The compiled one-pass kernel for a constraint form ('S' or 'NS') and dimension (1-3)."""
    return _STEPS[(form, dim)]


def multipliers_and_step_s(x, *args):
    """Smooth form, dimension taken from x (convenience for tests)."""
    return _STEPS[("S", x.shape[1])](x, *args)


def multipliers_and_step_ns(x, *args):
    """Non-smooth form, dimension taken from x (convenience for tests)."""
    return _STEPS[("NS", x.shape[1])](x, *args)


# ---- nested methods: NAP (2.16) and NAV (2.17) ----------------------------------------------
#
# Both linearise every constraint about the outer iterate X^p (2.15). With D = Y_i - Y_j for
# the inner iterate Y and D^p = X^p_i - X^p_j:
#
#     S:   phi^p = d_ij^2 + |D^p|^2 - 2 D^p.D,        grad_{Y_i} phi^p = -2 D^p
#     NS:  phi^p = d_ij - D^p.D / |D^p|,              grad_{Y_i} phi^p = -D^p / |D^p|
#
# (swapping i and j negates D and D^p, so phi^p is bitwise symmetric like phi). One inner step,
# multipliers first as in the DAHA kernel:
#
#     lambda^{p,n} = max(0, lambda^{p,n-1} + beta phi^p(Y^{p,n}))
#     Y_i^{p,n+1} = cy Y_i + cp X^p_i - cw (w_i - Xbar) - cf sum_j lambda_ij grad_{Y_i} phi^p
#
#   NAP (2.16a): Y = X^{p,n};  cy = 1, cp = 0, cw = alpha, cf = alpha, w = Y (grad W at Y, Xbar of Y)
#   NAV (2.17a), written for Y = X^p + tau V (so V = (Y - X^p)/tau):
#                cy = 1 - alpha, cp = alpha, cw = alpha tau, cf = alpha tau^2, w = X^p (Xbar of X^p)
#
# w_i - Xbar is grad W (``kernels.potential``): the point potential's w_i - P (P given as xbar),
# gravity's m_i g e_b. A container's walls are linearised about X^p like the pairs (2.15):
# phi^p_iw = c_i (d_i/2 - s_iw(X^p) - n_iw(X^p).(Y_i - X^p_i)), grad_{Y_i} phi^p_iw = -c_i n_iw(X^p)
# (``kernels.walls``; exact for a plane), with lambda_iw updated as the pairs'.
#
# Statistics as in the DAHA kernel: exact sums of Y^{n+1} (b rows), |Y^{n+1}-Y^n|^2, |Y^n|^2; max
# step^2 and max real overlap at Y^n.

NAP = 0
NAV = 1


def nested_coefficients(method, alpha, tau):
    """(cy, cp, cw, cf) of the inner update for 'nap' or 'nav'."""
    if method == "nap":
        return 1.0, 0.0, alpha, alpha
    if method == "nav":
        return 1.0 - alpha, alpha, alpha * tau, alpha * tau * tau
    raise ValueError(f"not a nested method: {method!r}")


@njit(cache=True, inline="always")
def _nested_step(form, dim, kind, y, x_lin, y_new, n_local, diam, pair_offsets, pair_j,
                 pair_lambda, walls, wall_lambda, xbar, pot, cy, cp, cw, cf, beta, update_lambda,
                 acc, maxima):
    cols = exactsum.columns(acc)  # the per-sphere sums, summed a block of spheres at a time
    gravity = pot[potential.POT_KIND] == potential.GRAVITY
    max_step2 = 0.0
    min_ratio2 = 1.0
    wall_overlap = 0.0
    n_active = 0
    f = np.zeros(dim)
    for i in range(n_local):
        f[:] = 0.0
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            j = pair_j[e]
            r2 = 0.0
            rp2 = 0.0
            dot = 0.0
            for k in range(dim):
                d = y[i, k] - y[j, k]
                dp = x_lin[i, k] - x_lin[j, k]
                r2 += d * d
                rp2 += dp * dp
                dot += dp * d
            dij = 0.5 * (diam[i] + diam[j])
            rp = 0.0
            if form == SMOOTH:
                phi = dij * dij + rp2 - 2.0 * dot
            else:
                rp = np.sqrt(rp2)
                phi = dij - dot / rp if rp > 0.0 else dij
            lam = pair_lambda[e]
            if update_lambda:
                lam = lam + beta * phi
                if lam < 0.0:
                    lam = 0.0
                pair_lambda[e] = lam
            if r2 < dij * dij:  # real overlap at Y^n, for the metric
                if r2 < min_ratio2 * (dij * dij):
                    min_ratio2 = r2 / (dij * dij)
            if lam > 0.0:
                n_active += 1
                if form == SMOOTH:
                    g = 2.0 * lam
                    for k in range(dim):
                        f[k] -= g * (x_lin[i, k] - x_lin[j, k])
                elif rp > 0.0:
                    g = lam / rp
                    for k in range(dim):
                        f[k] -= g * (x_lin[i, k] - x_lin[j, k])
        # the container's walls, linearised about X^p as the pairs (2.15): with s^p, n^p the
        # gap and inward normal at X^p_i, phi^p_iw(Y) = c_i (d_i/2 - s^p - n^p.(Y_i - X^p_i)),
        # grad_{Y_i} phi^p_iw = -c_i n^p; lambda_iw by the pairs' rule, a contact counts 2
        if walls.shape[0] > 0:
            di = diam[i]
            p0, p1, p2 = coordinates(dim, x_lin, i)
            y0, y1, y2 = coordinates(dim, y, i)
            for wall in range(walls.shape[0]):
                sp, n0, n1, n2, curv = walls_mod.gap(dim, walls, wall, p0, p1, p2)
                phi, c = walls_mod.wall_constraint(form == SMOOTH, di, sp + n0 * (y0 - p0)
                                                   + n1 * (y1 - p1) + n2 * (y2 - p2))
                lam = wall_lambda[i, wall]
                if update_lambda:
                    lam = lam + beta * phi
                    if lam < 0.0:
                        lam = 0.0
                    wall_lambda[i, wall] = lam
                s = walls_mod.gap(dim, walls, wall, y0, y1, y2)[0]  # real overlap at Y^n
                if s < 0.5 * di and (0.5 * di - s) > wall_overlap * (0.5 * di):
                    wall_overlap = (0.5 * di - s) / (0.5 * di)
                if lam > 0.0:
                    n_active += 2
                    g = lam * c  # lam grad_i phi^p_iw = -g n^p
                    f[0] -= g * n0
                    if dim > 1:
                        f[1] -= g * n1
                    if dim > 2:
                        f[2] -= g * n2
        weight = 0.0
        if gravity:  # grad W = m_i g along the last axis, and sphere i's share of W / g at Y^n
            weight = potential.mass(dim, pot, diam[i]) * pot[potential.POT_G]
            y0, y1, y2 = coordinates(dim, y, i)
            exactsum.put(cols, dim + 2, i, potential.height_energy(dim, pot, diam[i], y0, y1, y2))
        dx2 = 0.0
        yy2 = 0.0
        for k in range(dim):
            yi = y[i, k]
            if gravity:
                gw = weight if k == dim - 1 else 0.0
            else:  # w - A: the centre Xbar or the point P (``kernels.potential``)
                w = x_lin[i, k] if kind == NAV else yi
                gw = w - xbar[k]
            yn = cy * yi + cp * x_lin[i, k] - cw * gw - cf * f[k]
            y_new[i, k] = yn
            exactsum.put(cols, k, i, yn)
            dx2 += (yn - yi) * (yn - yi)
            yy2 += yi * yi
        exactsum.put(cols, dim, i, dx2)
        exactsum.put(cols, dim + 1, i, yy2)
        if exactsum.block_ends(i):
            exactsum.add_block(cols, acc)
        if dx2 > max_step2 or dx2 != dx2:
            max_step2 = dx2
    exactsum.flush_columns(cols, acc, n_local)
    maxima[MAX_STEP2] = max_step2
    max_overlap = 1.0 - np.sqrt(min_ratio2)
    if wall_overlap > max_overlap:  # (a NaN max_overlap stays NaN: the guard must see it)
        max_overlap = wall_overlap
    maxima[MAX_OVERLAP] = max_overlap
    return n_active


# The scene's kernels: the container's walls and the potential as the DAHA kernels take them.
@njit(cache=True)
def nap_s(y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx):
    return _nested_step(SMOOTH, y.shape[1], NAP, y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx)


@njit(cache=True)
def nap_ns(y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx):
    return _nested_step(NONSMOOTH, y.shape[1], NAP, y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx)


@njit(cache=True)
def nav_s(y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx):
    return _nested_step(SMOOTH, y.shape[1], NAV, y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx)


@njit(cache=True)
def nav_ns(y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx):
    return _nested_step(NONSMOOTH, y.shape[1], NAV, y, x_lin, y_new, n_local, diam, po, pj, pl, wa, wl, xbar, pot, cy, cp, cw, cf, beta, upd, acc, mx)


_NESTED = {("nap", "S"): nap_s, ("nap", "NS"): nap_ns, ("nav", "S"): nav_s, ("nav", "NS"): nav_ns}


def nested_step(method, form):
    """The compiled inner-step kernel of NAP or NAV for a form.

    Arguments: (y, x_lin, y_new, n_local, diam, pair_offsets, pair_j, pair_lambda, walls,
    wall_lambda, xbar, pot, cy, cp, cw, cf, beta, update_lambda, acc, maxima); shapes as the DAHA
    kernels (the container and the potential as they take them: no wall rows and pot = 0 for the
    paper's setting), x_lin (n_total, b) the linearisation point X^p (ghost rows too). Under
    gravity it adds W / g at Y^n to row b+2 of acc. The nested methods are about the paper's
    small-N comparisons, so these kernels are written for clarity (runtime dimension loops).
    """
    return _NESTED[(method, form)]


# ---- metrics of a configuration and its multipliers (one pass, on demand) ---------------------
#
# For each local particle i, with g_i = grad_{X_i} L = (X_i - Xbar) + sum_j lambda_ij grad_{X_i} phi_ij:
#   exact rows  KKT2 = sum_i |g_i|^2,  GW2 = sum_i |X_i - Xbar|^2 (= |grad W|^2 = 2 W),
#               CF2 = sum_i c_i^2, c_i = sum_j lambda_ij |grad_{X_i} phi_ij| (the magnitudes of
#               the contact forces on sphere i, the scale of the force balance g_i = 0)
#   maxima      max overlap (d_ij - r)/d_ij, complementarity max lambda_ij |phi_ij|, max lambda_ij
#   per particle pressure mu_i = sum_j lambda_ij (paper, Fig. 9), active contacts and the net
#               force |g_i| (where the KKT residual sits: a packing still rearranging carries it
#               on a few spheres, an unconverged multiplier scale on all of them)
# lam_scale turns the stored multipliers into those of the KKT system (2.4): 1 for DAHA, AHA
# and NAP; tau for NAV, whose multipliers belong to the velocity problem (2.6): lambda = tau mu.
# lambda_mode: LAMBDA_STORED uses the stored multipliers; LAMBDA_UPDATE first brings them up
# to date with X by (2.10b), exactly as the step kernel would, and stores them (the end of a
# DAHA run: lambda^n of the final X^n); LAMBDA_PEEK uses those updated values without storing
# them (a check in the middle of a run, which must not change the trajectory). LAMBDA_FORCE
# (the fire-al schedule) uses the augmented Lagrangian's force multipliers, the ones the step
# kernel moves the spheres with, mu = max(0, lambda + pen max(lambda, lam_floor) phi / d_ij^p)
# (p = 2 for S, 1 for NS), and only on pairs in contact to contact_tol (gap (r - d_ij) / d_ij
# <= contact_tol; a pair farther apart carries no multiplier), without storing them.

LAMBDA_STORED, LAMBDA_UPDATE, LAMBDA_PEEK, LAMBDA_FORCE = 0, 1, 2, 3
# exact rows: KKT2, GW2, the overlap measure sum_{i<j} |B_i ∩ B_j| (each pair once, by the owner of
# its lower gid) and the spheres' measure sum_i |B_i|, for the paper's A (Definition 4.1)
MET_KKT2, MET_GW2, MET_OVERLAP_MEASURE, MET_SPHERE_MEASURE, MET_CF2 = 0, 1, 2, 3, 4
# ... and under gravity W / g = sum m_i (h_i - h_0) (``kernels.potential``; GW2 is |grad W|^2)
MET_WPOT = 5
N_MET_EXACT = 6
MET_OVERLAP, MET_COMPL, MET_LAMBDA, MET_NET = 0, 1, 2, 3
N_MET_MAX = 4


@njit(cache=True, inline="always")
def _multiplier(form, lam, phi, size, apart, beta, lambda_mode, pen, lam_floor):
    """A constraint's multiplier under ``lambda_mode`` (see above), before lam_scale: the stored
    lambda, lambda + beta phi clipped at 0 ((2.10b), UPDATE and PEEK), or the force multiplier
    (FORCE) with phi in units of size^p, 0 when the constraint is ``apart`` (not in contact)."""
    if lambda_mode == LAMBDA_FORCE:
        unit = 1.0 / (size * size) if form == SMOOTH else 1.0 / size
        w = lam if lam > lam_floor else lam_floor
        lam = lam + pen * w * phi * unit
        if lam < 0.0:
            lam = 0.0
        if apart:
            lam = 0.0
    elif lambda_mode != LAMBDA_STORED:
        lam = lam + beta * phi
        if lam < 0.0:
            lam = 0.0
    return lam


@njit(cache=True, inline="always")
def entry_multiplier(form, lam, phi, r2, dij, beta, lambda_mode, pen, lam_floor, contact_tol):
    """The multiplier of one stored pair (``_multiplier``; size d_ij, in contact to contact_tol
    when r <= d_ij (1 + tol))."""
    return _multiplier(form, lam, phi, dij, r2 > (dij * (1.0 + contact_tol)) ** 2, beta, lambda_mode, pen,
                       lam_floor)


@njit(cache=True, inline="always")
def wall_multiplier(form, lam, phi, s, di, beta, lambda_mode, pen, lam_floor, contact_tol):
    """The multiplier of a wall constraint of a sphere of diameter di at distance s inside
    (``kernels.walls``; ``_multiplier`` with size d_i, in contact when s <= (d_i/2)(1 + tol))."""
    return _multiplier(form, lam, phi, di, s > 0.5 * di * (1.0 + contact_tol), beta, lambda_mode, pen,
                       lam_floor)


@njit(cache=True, inline="always")
def _pair_metrics(form, x, n_local, diam, gid, pair_offsets, pair_j, pair_lambda, walls,
                  wall_lambda, xbar, pot, beta, lambda_mode, lam_scale, pen, lam_floor, contact_tol,
                  measures_a, acc, maxima, pressure, contacts, net_force, pair_force, wall_force):
    dim = x.shape[1]
    keep_pair_force = pair_force.shape[0] > 0
    keep_wall_force = wall_force.shape[0] > 0
    cols = exactsum.columns(acc)  # the per-sphere sums, summed a block of spheres at a time
    g = np.zeros(dim)
    d = np.zeros(dim)
    max_overlap = 0.0
    wall_overlap = 0.0
    min_ratio2 = 1.0
    max_compl = 0.0
    max_lam = 0.0
    max_net2 = 0.0
    n_active = 0
    gravity = pot[potential.POT_KIND] == potential.GRAVITY
    for i in range(n_local):
        gw2 = 0.0
        if gravity:  # grad W = m_i g along the last axis (``kernels.potential``)
            for k in range(dim):
                g[k] = 0.0
            g[dim - 1] = potential.mass(dim, pot, diam[i]) * pot[potential.POT_G]
            xi0, xi1, xi2 = coordinates(dim, x, i)
            exactsum.put(cols, MET_WPOT, i, potential.height_energy(dim, pot, diam[i], xi0, xi1, xi2))
        else:
            for k in range(dim):
                g[k] = x[i, k] - xbar[k]
        for k in range(dim):
            gw2 += g[k] * g[k]
        mu = 0.0
        cf = 0.0
        nc = 0
        di = diam[i]
        lens = 0.0
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            j = pair_j[e]
            r2 = 0.0
            for k in range(dim):
                d[k] = x[i, k] - x[j, k]
                r2 += d[k] * d[k]
            dij = 0.5 * (di + diam[j])
            phi, r = constraint(form, dij, r2)
            lam = entry_multiplier(form, pair_lambda[e], phi, r2, dij, beta, lambda_mode, pen,
                                   lam_floor, contact_tol)
            if lambda_mode == LAMBDA_UPDATE:
                pair_lambda[e] = lam
            lam = lam * lam_scale
            if keep_pair_force:
                pair_force[e] = lam
            if phi > 0.0:
                if form == SMOOTH:
                    if r2 < min_ratio2 * (dij * dij):
                        min_ratio2 = r2 / (dij * dij)
                elif phi > max_overlap * dij:
                    max_overlap = phi / dij
                if measures_a and gid[i] < gid[j]:  # each pair once, by its lower gid's owner
                    lens += metrics.intersection(dim, np.sqrt(r2), 0.5 * diam[j], 0.5 * di)
            if lam > 0.0:
                n_active += 1
                mu += lam
                nc += 1
                c = lam * abs(phi)
                if c > max_compl:
                    max_compl = c
                if lam > max_lam:
                    max_lam = lam
                if form == SMOOTH:
                    cf += 2.0 * lam * np.sqrt(r2)
                    for k in range(dim):
                        g[k] -= 2.0 * lam * d[k]
                elif r > 0.0:
                    cf += lam
                    for k in range(dim):
                        g[k] -= lam * d[k] / r
        # the container's walls (``kernels.walls``): lambda_iw grad_i phi_iw = -lambda_iw c n_iw
        x0, x1, x2 = coordinates(dim, x, i)
        wf = 0.0
        for wall in range(walls.shape[0]):
            s, n0, n1, n2, curv = walls_mod.gap(dim, walls, wall, x0, x1, x2)
            phi, cw = walls_mod.wall_constraint(form == SMOOTH, di, s)
            lam = wall_multiplier(form, wall_lambda[i, wall], phi, s, di, beta, lambda_mode, pen,
                                  lam_floor, contact_tol)
            if lambda_mode == LAMBDA_UPDATE:
                wall_lambda[i, wall] = lam
            lam = lam * lam_scale
            if phi > 0.0 and (0.5 * di - s) > wall_overlap * (0.5 * di):
                wall_overlap = (0.5 * di - s) / (0.5 * di)
            if lam > 0.0:
                n_active += 2
                nc += 1
                c = lam * abs(phi)
                if c > max_compl:
                    max_compl = c
                if lam > max_lam:
                    max_lam = lam
                cf += lam * cw
                wf += lam * cw
                g[0] -= lam * cw * n0
                if dim > 1:
                    g[1] -= lam * cw * n1
                if dim > 2:
                    g[2] -= lam * cw * n2
        if keep_wall_force:
            wall_force[i] = wf
        kkt2 = 0.0
        for k in range(dim):
            kkt2 += g[k] * g[k]
        exactsum.put(cols, MET_KKT2, i, kkt2)
        exactsum.put(cols, MET_GW2, i, gw2)
        exactsum.put(cols, MET_CF2, i, cf * cf)
        exactsum.put(cols, MET_OVERLAP_MEASURE, i, lens)
        if measures_a:
            exactsum.put(cols, MET_SPHERE_MEASURE, i, metrics.ball_volume(dim, 0.5 * di))
        if exactsum.block_ends(i):
            exactsum.add_block(cols, acc)
        pressure[i] = mu
        contacts[i] = nc
        net_force[i] = np.sqrt(kkt2)
        if kkt2 > max_net2:
            max_net2 = kkt2
    exactsum.flush_columns(cols, acc, n_local)
    if form == SMOOTH:
        max_overlap = 1.0 - np.sqrt(min_ratio2)
    if wall_overlap > max_overlap:
        max_overlap = wall_overlap
    maxima[MET_OVERLAP] = max_overlap
    maxima[MET_COMPL] = max_compl
    maxima[MET_LAMBDA] = max_lam
    maxima[MET_NET] = np.sqrt(max_net2)
    return n_active


@njit(cache=True)
def metrics_s(x, n_local, diam, gid, po, pj, pl, wa, wl, xbar, pot, beta, upd, scale, pen, floor, tol, area, acc,
              mx, pressure, contacts, net_force, pair_force, wall_force):
    return _pair_metrics(SMOOTH, x, n_local, diam, gid, po, pj, pl, wa, wl, xbar, pot, beta, upd, scale, pen, floor,
                         tol, area, acc, mx, pressure, contacts, net_force, pair_force, wall_force)


@njit(cache=True)
def metrics_ns(x, n_local, diam, gid, po, pj, pl, wa, wl, xbar, pot, beta, upd, scale, pen, floor, tol, area, acc,
               mx, pressure, contacts, net_force, pair_force, wall_force):
    return _pair_metrics(NONSMOOTH, x, n_local, diam, gid, po, pj, pl, wa, wl, xbar, pot, beta, upd, scale, pen, floor,
                         tol, area, acc, mx, pressure, contacts, net_force, pair_force, wall_force)


def pair_metrics(form):
    """The compiled metrics pass for a form (any dimension). Arguments: (x, n_local, diam, gid
    (n_total,), pair_offsets, pair_j, pair_lambda, walls, wall_lambda (``kernels.walls``: the
    walls count in every figure like pairs), xbar, pot (``kernels.potential``), beta, lambda_mode, lam_scale, pen, lam_floor,
    contact_tol (LAMBDA_FORCE only), measures_a (with the
    overlap and sphere measures of the paper's A: the costly part, lens areas), acc (5, NBINS+1), maxima
    (N_MET_MAX,), pressure (n_local,), contacts int32 (n_local,), net_force (n_local,): |g_i|,
    pair_force: each row entry's multiplier (the one pressure sums), shape (pair_offsets[n_local],),
    or shape (0,) to skip), wall_force: each local sphere's sum_w lambda_iw |grad phi_iw| (the
    walls' push on it), shape (n_local,) or (0,) to skip); returns the number of row entries
    with lambda > 0 (a wall contact counts 2)."""
    return metrics_s if form == "S" else metrics_ns


@njit(cache=True)
def change_sums(x, x_ref, n_local, acc):
    """Exact sums of |x_i - x_ref_i|^2 (row 0) and |x_ref_i|^2 (row 1) over local particles."""
    b = x.shape[1]
    fbuf = exactsum.staging(acc)
    for i in range(n_local):
        d2 = 0.0
        r2 = 0.0
        for k in range(b):
            d2 += (x[i, k] - x_ref[i, k]) * (x[i, k] - x_ref[i, k])
            r2 += x_ref[i, k] * x_ref[i, k]
        exactsum.add(fbuf, acc, 0, d2)
        exactsum.add(fbuf, acc, 1, r2)
    exactsum.flush(fbuf, acc)


@njit(cache=True)
def local_sums(x, n_local, acc):
    """Exact sums of X (b rows) and |X|^2 (row b) over local particles, added to acc."""
    b = x.shape[1]
    fbuf = exactsum.staging(acc)
    for i in range(n_local):
        s = 0.0
        for k in range(b):
            exactsum.add(fbuf, acc, k, x[i, k])
            s += x[i, k] * x[i, k]
        exactsum.add(fbuf, acc, b, s)
    exactsum.flush(fbuf, acc)


@njit(cache=True)
def centred_sums(x, n_local, xbar, acc):
    """Exact sum of |X_i - Xbar|^2 over local particles into acc row 0 (W = half of it)."""
    b = x.shape[1]
    fbuf = exactsum.staging(acc)
    for i in range(n_local):
        s = 0.0
        for k in range(b):
            s += (x[i, k] - xbar[k]) * (x[i, k] - xbar[k])
        exactsum.add(fbuf, acc, 0, s)
    exactsum.flush(fbuf, acc)
