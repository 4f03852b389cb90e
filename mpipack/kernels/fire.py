"""Numba kernel of the "fire-al" schedule (``schedule``): one pass that does DAHA's gamma form
or an augmented-Lagrangian step with FIRE momentum. Serial array code: never imports MPI.

Notation as in ``kernels``: phi_ij (S: d_ij^2 - r^2, NS: d_ij - r), grad_i phi_ij, and
|grad phi|^2 = 4 r^2 (S) or 1 (NS), |Hess phi| = 2 (S) or 1/r (NS). For every row entry:

    dual      lam   = max(0, lam + beta wd phi~)       weighted_dual: wd = max(lam, lam_floor),
                                                       phi~ = phi / d_ij^p (p = 2 for S, 1 for
                                                       NS: phi in units of the pair's size);
                                                       else wd = 1, phi~ = phi; skipped when
                                                       not update_lambda
    weight    w     = max(lam, lam_floor)              (lam_floor = 0: the paper's lambda)
    force     clip:     m = max(0, a3 lam + a4 w phi / d_ij^p)  (= a3 max(0, lam + rho phi),
                                                                rho = a4 w / (a3 d_ij^p): the
                                                                trial multiplier of the
                                                                augmented Lagrangian, penalty rho)
              not clip: m = a3 lam + a4 w phi if lam > 0 else 0  (DAHA (2.10a), gamma form)
    per particle
              G_i = -(a3 (X_i - Xbar) + sum_j m grad_i phi_ij)
              D_i = (a1 - 1) X_i^n + a2 X_i^{n-1} + G_i,   |D_i| <= vmax (if vmax > 0)
              X_i^{n+1} = X_i^n + D_i

With a1 = 2/(1+c/2), a2 = -(1-c/2)/(1+c/2), a3 = alpha^2/(1+c/2), a4 = gamma^2/(1+c/2), no
floor, no clip and vmax = 0 this is DAHA (2.10) exactly (up to rounding). FIRE in displacement
form sets a1 = 1 + a, a2 = -a (velocity mixing) and a3 = b (step times step).
At a KKT point phi lam = 0 and phi <= 0, so m = a3 lam, G = -a3 grad L = 0 and D = 0 whatever
the floor, the clip and the cap are: the fixed points are the KKT points.

A pass has two halves. The first computes the terms of each pair once (over the rows' half
list: a pair of two local spheres appears in both rows) and writes them to both of its entries;
the second sums each sphere's row of terms in the row's partner-gid order, as a pass over the
whole rows would, so the bits do not depend on the partition (nor on the half list), and each
pair's arithmetic (its constraint, the dual step, the division by d_ij^p, the branches) is done
once instead of twice (``mpipack bench --phases``: docs/benchmarks.md). In L-BFGS's gradient
pass the terms are the force's components, and its second half reads no partner position.

Reduced figures (block "step" of the exact sums, block "step" of the maxima):
    exact   sum X^{n+1} (b rows), sum |X^{n+1}-X^n|^2, sum |X^n|^2, power sum G.V (V = X^n -
            X^{n-1}), sum |G|^2
    maxima  max |D_i|^2, max overlap (d_ij - r)/d_ij at X^n,
            T = max_i sum_{lam>0 or phi>0} |grad phi|^2 (the dual gain of a row),
            K = max_i a3 + 2 sum_{m != 0} (a4 w |grad phi|^2 [/ d_ij^p under clip] + |m| |Hess phi|)
            (Gershgorin row)
"""

import numpy as np

from mpipack.jit import njit
from mpipack.parallel import exactsum
from mpipack.kernels.daha import NONSMOOTH, SMOOTH, constraint, coordinates, gradient_scale, separation
from mpipack.kernels import walls as walls_mod
from mpipack.kernels import potential

# exact rows after the b rows of sum X^{n+1}
ACC_DX2, ACC_XX2, ACC_POWER, ACC_FORCE2 = 0, 1, 2, 3
N_ACC = 4
ACC_WPOT = 4  # under gravity only: sum m_i (h_i - h_0) of X^n (``kernels.potential``), every pass
# maxima
MAX_STEP2, MAX_OVERLAP, MAX_GAIN, MAX_ROW = 0, 1, 2, 3
N_MAX = 4


@njit(cache=True, inline="always")
def _coordinate(a1, a2, a3, xi, xp, pw, f):
    """One coordinate of a sphere's update: G = -(a3 grad W + F) (pw: grad W's coordinate,
    X_i - Xbar for the centre) and the displacement D = (a1 - 1) X^n + a2 X^{n-1} + G, returned
    as (D, D^2, (X^n)^2, G (X^n - X^{n-1}), G^2), the terms of the reduced sums |D|^2, |X^n|^2,
    the power G.V and |G|^2."""
    g = -(a3 * pw + f)
    d = (a1 - 1.0) * xi + a2 * xp + g
    return d, d * d, xi * xi, g * (xi - xp), g * g


@njit(cache=True, inline="always")
def _term(lam, phi, phin, g2, hess, unit, a3, a4, beta, lam_floor, clip, weighted_dual, update_lambda):
    """One constraint's part of a pass (a pair's row entry or a sphere's wall), see the module
    docstring: (lam after the dual step, the force multiplier m, its share of the row's dual
    gain, its share of the Gershgorin row). phin = phi unit, unit = 1 / (size)^p under clip."""
    if update_lambda:
        wd = 1.0
        pd = phi
        if weighted_dual:
            wd = lam if lam > lam_floor else lam_floor
            pd = phin
        lam = lam + beta * wd * pd
        if lam < 0.0:
            lam = 0.0
    w = lam if lam > lam_floor else lam_floor
    if clip:
        m = a3 * lam + a4 * w * phin
        if m < 0.0:
            m = 0.0
    elif lam > 0.0:
        m = a3 * lam + a4 * w * phi
    else:
        m = 0.0
    # selects, not jumps (both sides computed): in a packing whether a pair's lambda or phi
    # is positive is a coin toss
    gain = g2 if (lam > 0.0) | (phi > 0.0) else 0.0
    row_m = a4 * w * g2 * unit + abs(m) * hess
    row = row_m if m != 0.0 else 0.0
    return lam, m, gain, row


# rows of the pair terms' buffer (``pairs``' terms), one column per row entry: a FIRE or
# multiplier pass's factor g of the force m grad_i phi_ij = -g (X_i - X_j) (row 0), the dual
# gain's (row b) and the Gershgorin row's (row b + 1) shares; a gradient pass's force as b
# components (rows 0 .. b-1)


def n_terms(dim):
    """The rows of the terms buffer in dimension ``dim``."""
    return dim + 2


@njit(cache=True, inline="always")
def _pair_math(form, r2, dij, lam0, a3, a4, beta, lam_floor, clip, weighted_dual, update_lambda):
    """One pair's arithmetic (see the module docstring) from its squared distance r2, d_ij and
    lambda: (lambda after the dual step, the force factor g with m grad_i phi_ij = -g (X_i -
    X_j), the row's dual gain and Gershgorin shares, phi, d_ij^2). No memory access: the first
    half of a pass runs it over a block of pairs at a time, in vector instructions."""
    phi, r = constraint(form, dij, r2)
    # |grad_i phi|^2 and the curvature of phi along the pair (the Gershgorin row)
    if form == SMOOTH:
        g2 = 4.0 * r2
        hess = 2.0
    else:
        g2 = 1.0
        hess = 1.0 / r if r > 0.0 else 0.0
    # the penalty's phi in units of the pair's diameter (clip form): phi / d_ij^p
    dd = dij * dij
    unit = 1.0
    if clip:
        unit = 1.0 / dd if form == SMOOTH else 1.0 / dij
    # no branch for an entry of the skin's shell (phi <= 0, lambda = 0: whether a pair
    # overlaps is a coin toss in a packing): its dual step leaves lambda at 0, and its force,
    # gain and row are exact zeros
    lam, m, gain, row = _term(lam0, phi, phi * unit, g2, hess, unit, a3, a4, beta, lam_floor, clip,
                              weighted_dual, update_lambda)
    return lam, gradient_scale(form, m, r), gain, row, phi, dd


@njit(cache=True, inline="always")
def _pair(form, dim, x, xi0, xi1, xi2, di, j, diam, lam0, a3, a4, beta, lam_floor, clip, weighted_dual,
          update_lambda):
    """One pair's part of a pass (see the module docstring), from X_i (scalars), d_i, partner
    j and lambda: (X_i - X_j as three scalars, lambda after the dual step, the force factor g
    with m grad_i phi_ij = -g (X_i - X_j), the row's dual gain and Gershgorin shares, phi, the
    squared distance, d_ij^2). A function of the pair alone: from the partner's side only the
    separation's sign differs."""
    d0, d1, d2, r2 = separation(dim, x, xi0, xi1, xi2, j)
    dij = 0.5 * (di + diam[j])
    lam, g, gain, row, phi, dd = _pair_math(form, r2, dij, lam0, a3, a4, beta, lam_floor, clip, weighted_dual,
                                            update_lambda)
    return d0, d1, d2, lam, g, gain, row, phi, r2, dd


@njit(cache=True, inline="always")
def _min_ratio(phi, r2, dd, min_ratio2):
    """min(min_ratio2, r2 / dd) over overlapping pairs (phi > 0): an exact minimum whatever the
    order of the pairs; the division only where the ratio may be below it (the test's margin
    covers its rounding)."""
    if (phi > 0.0) & (r2 <= min_ratio2 * dd * (1.0 + 1e-12)):
        ratio2 = r2 / dd
        if ratio2 < min_ratio2:
            return ratio2
    return min_ratio2


# The first half of a pass takes the half list a block of PAIR_BLOCK pairs at a time, through
# a scratch array of _W_ROWS rows (20 kB: in the L1 cache)
PAIR_BLOCK = 256
_W_D = 0  # rows 0 .. 2: X_i - X_j, then (without figures) the force's components
# |X_i - X_j|^2, d_ij, lambda, (with figures) g and the gain's and row's shares, the overlap ratio
_W_R2, _W_DIJ, _W_LAM, _W_G, _W_GAIN, _W_ROW, _W_RATIO = 3, 4, 5, 6, 7, 8, 9
_W_ROWS = 10


@njit(cache=True, inline="always")
def _pair_terms(form, dim, x, diam, pair_lambda, half_i, half_e, half_j, half_f, terms, a3, a4,
                beta, lam_floor, clip, weighted_dual, update_lambda, figures):
    """The first half of a pass over the half list (``pair_halves``): every pair's part once,
    written to the pair's entry and to its mirror (its entry in the partner's row): lambda,
    and in ``terms`` the force m grad_i phi_ij (its negative in the mirror), and with
    ``figures`` the gain's and the row's shares. Both entries get the bits that a walk of both
    whole rows would give them. Returns (entries with lambda > 0, the min ratio of
    ``_min_ratio``). Inlined with literal flags where the pass calls it, so that LLVM folds
    their branches.

    A block of PAIR_BLOCK listed pairs at a time, in three loops: the gather (separations,
    d_ij, lambdas into the scratch's rows), the arithmetic (``_pair_math`` over the rows
    alone: vector instructions, several square roots and divisions at once; one pair at a
    time, they queued on the divider and bounded the pass: docs/benchmarks.md, session 42) and
    the scatter to each pair's two entries. The min ratio is the minimum of each overlapping
    pair's r2 / d_ij^2, computed for every pair in the arithmetic: ``_min_ratio``'s value,
    without its loop-carried multiply and test."""
    n_active = 0
    min_ratio2 = 1.0
    work = np.empty((_W_ROWS, PAIR_BLOCK))
    w_d0, w_d1, w_d2 = work[_W_D], work[_W_D + 1], work[_W_D + 2]
    w_r2, w_dij, w_lam, w_g = work[_W_R2], work[_W_DIJ], work[_W_LAM], work[_W_G]
    w_gain, w_row, w_ratio = work[_W_GAIN], work[_W_ROW], work[_W_RATIO]
    n_half = half_e.shape[0]
    for k0 in range(0, n_half, PAIR_BLOCK):
        n_block = min(PAIR_BLOCK, n_half - k0)
        # unsigned indices: numba wraps a signed index around (x[-1]) with a test and the
        # array's shape
        for t in range(n_block):
            k = k0 + t
            i = np.uint64(half_i[k])
            xi0, xi1, xi2 = coordinates(dim, x, i)
            j = np.uint64(half_j[k])
            d0, d1, d2, r2 = separation(dim, x, xi0, xi1, xi2, j)
            w_d0[t] = d0
            if dim > 1:
                w_d1[t] = d1
            if dim > 2:
                w_d2[t] = d2
            w_r2[t] = r2
            w_dij[t] = 0.5 * (diam[i] + diam[j])
            w_lam[t] = pair_lambda[np.uint64(half_e[k])]
        for t in range(n_block):
            lam, g, gain, row, phi, dd = _pair_math(form, w_r2[t], w_dij[t], w_lam[t], a3, a4, beta, lam_floor,
                                                    clip, weighted_dual, update_lambda)
            w_lam[t] = lam
            w_ratio[t] = w_r2[t] / dd if phi > 0.0 else 1.0
            if figures:
                w_g[t] = g
                w_gain[t] = gain
                w_row[t] = row
            else:
                # the force's components (the partner's entry gets the opposite ones: X_j - X_i
                # = -(X_i - X_j) and g (-d) = -(g d) exactly)
                w_d0[t] = g * w_d0[t]
                if dim > 1:
                    w_d1[t] = g * w_d1[t]
                if dim > 2:
                    w_d2[t] = g * w_d2[t]
        for t in range(n_block):
            k = k0 + t
            e = np.uint64(half_e[k])
            f = half_f[k]
            lam = w_lam[t]
            both = 1 if f < 0 else 2
            n_active += both if lam > 0.0 else 0
            ratio2 = w_ratio[t]
            min_ratio2 = ratio2 if ratio2 < min_ratio2 else min_ratio2
            if update_lambda:
                pair_lambda[e] = lam
            if figures:
                terms[0, e] = w_g[t]
                terms[dim, e] = w_gain[t]
                terms[dim + 1, e] = w_row[t]
            else:
                terms[0, e] = w_d0[t]
                if dim > 1:
                    terms[1, e] = w_d1[t]
                if dim > 2:
                    terms[2, e] = w_d2[t]
            if f >= 0:
                fu = np.uint64(f)
                if update_lambda:
                    pair_lambda[fu] = lam
                if figures:
                    terms[0, fu] = w_g[t]
                    terms[dim, fu] = w_gain[t]
                    terms[dim + 1, fu] = w_row[t]
                else:
                    terms[0, fu] = -w_d0[t]
                    if dim > 1:
                        terms[1, fu] = -w_d1[t]
                    if dim > 2:
                        terms[2, fu] = -w_d2[t]
    return n_active, min_ratio2


@njit(cache=True, inline="always")
def _row_sums(dim, x, xi0, xi1, xi2, e0, e1, pair_j, terms, figures):
    """The second half of a pass, for one sphere: its row's pair terms summed in the row's
    (partner-gid) order, F_i = -sum_j g (X_i - X_j), and with ``figures`` the dual gain and the
    Gershgorin sum; as (F_i as three scalars, gain, row). With figures the terms hold g, and
    X_i - X_j is taken again here; without, the force's components."""
    f0 = 0.0
    f1 = 0.0
    f2 = 0.0
    gain = 0.0
    row = 0.0
    for e in range(np.uint64(e0), np.uint64(e1)):
        # a zero term adds exact zeros (the force is never -0.0: it starts at +0.0 and
        # x - x = +0.0)
        if figures:
            d0, d1, d2, _ = separation(dim, x, xi0, xi1, xi2, np.uint64(pair_j[e]))
            g = terms[0, e]
            f0 -= g * d0
            f1 -= g * d1
            f2 -= g * d2
            gain += terms[dim, e]
            row += terms[dim + 1, e]
        else:
            f0 -= terms[0, e]
            if dim > 1:
                f1 -= terms[1, e]
            if dim > 2:
                f2 -= terms[2, e]
    return f0, f1, f2, gain, row


@njit(cache=True, inline="always")
def _whole_row(form, dim, x, xi0, xi1, xi2, di, e0, e1, pair_j, diam, pair_lambda, a3, a4, beta, lam_floor,
               clip, weighted_dual, update_lambda, min_ratio2):
    """A pass's walk of one sphere's whole row, each pair's part computed here (the rows of a
    dense start, too many entries for a half list's memory: ``HALF_LIST_MAX_ROW``): the same
    bits as the two halves. Returns (F_i as three scalars, gain, row, entries with lambda > 0,
    min_ratio2)."""
    f0 = 0.0
    f1 = 0.0
    f2 = 0.0
    gain = 0.0
    row = 0.0
    n_active = 0
    for e in range(np.uint64(e0), np.uint64(e1)):
        d0, d1, d2, lam, g, gain_e, row_e, phi, r2, dd = _pair(
            form, dim, x, xi0, xi1, xi2, di, np.uint64(pair_j[e]), diam, pair_lambda[e], a3, a4, beta,
            lam_floor, clip, weighted_dual, update_lambda)
        min_ratio2 = _min_ratio(phi, r2, dd, min_ratio2)
        n_active += 1 if lam > 0.0 else 0
        if update_lambda:
            pair_lambda[e] = lam
        gain += gain_e
        row += row_e
        f0 -= g * d0
        f1 -= g * d1
        f2 -= g * d2
    return f0, f1, f2, gain, row, n_active, min_ratio2


@njit(cache=True, inline="always")
def _fire_al_step(form, dim, x, x_prev, x_new, n_local, diam, pair_offsets, pair_j, pair_lambda,
                  pairs, walls, wall_lambda, xbar, pot, a1, a2, a3, a4, beta, lam_floor, clip,
                  weighted_dual, vmax, update_lambda, acc, maxima, gradient_pass):
    # form and dim are compile-time constants of each wrapper below: LLVM removes the dead
    # branches and keeps the coordinates in scalars (with small arrays indexed by a runtime
    # range(dim) loop the pass took 8 - 10% longer, 3D N = 2000 and 2D N = 8000 states)
    cols = exactsum.columns(acc)  # the per-sphere sums, summed a block of spheres at a time
    gravity = pot[potential.POT_KIND] == potential.GRAVITY
    # a dual step of gain 0 leaves every lambda (>= 0) as it is, lam + 0 = lam for a finite
    # phi: skip its read-modify-write of the multipliers (the L-BFGS gradient passes, FIRE's
    # once c_b has grown; 16% of a 2D gradient pass, ``mpipack bench --phases``)
    update_lambda = update_lambda and beta != 0.0
    xb0 = xbar[0]
    xb1 = xbar[1] if dim > 1 else 0.0
    xb2 = xbar[2] if dim > 2 else 0.0
    max_step2 = 0.0
    wall_overlap = 0.0
    max_gain = 0.0
    max_row = 0.0
    # first every pair's part once (the half list), then every sphere's row sums and update;
    # or, without a half list, each sphere's whole row. The flags as literals in the two passes
    # of the fire phase (FIRE's with its dual step, and without: L-BFGS's gradient, FIRE's once
    # c_b has grown): their branches folded
    half_i, half_e, half_j, half_f, terms = pairs
    halves = half_e.shape[0] > 0
    n_active = 0
    min_ratio2 = 1.0
    if halves:
        if clip and weighted_dual and update_lambda:
            n_active, min_ratio2 = _pair_terms(form, dim, x, diam, pair_lambda, half_i, half_e,
                                               half_j, half_f, terms, a3, a4, beta, lam_floor, True, True, True,
                                               True)
        elif clip and weighted_dual and not gradient_pass:
            n_active, min_ratio2 = _pair_terms(form, dim, x, diam, pair_lambda, half_i, half_e,
                                               half_j, half_f, terms, a3, a4, beta, lam_floor, True, True, False,
                                               True)
        elif clip and weighted_dual:
            n_active, min_ratio2 = _pair_terms(form, dim, x, diam, pair_lambda, half_i, half_e,
                                               half_j, half_f, terms, a3, a4, beta, lam_floor, True, True, False,
                                               False)
        else:
            n_active, min_ratio2 = _pair_terms(form, dim, x, diam, pair_lambda, half_i, half_e,
                                               half_j, half_f, terms, a3, a4, beta, lam_floor, clip, weighted_dual,
                                               update_lambda, not gradient_pass)
    for i in range(n_local):
        xi0, xi1, xi2 = coordinates(dim, x, i)
        di = diam[i]
        e0, e1 = pair_offsets[i], pair_offsets[i + 1]
        if halves:
            if gradient_pass:  # (the force's components; no gain or row shares)
                f0, f1, f2, gain, row = _row_sums(dim, x, xi0, xi1, xi2, e0, e1, pair_j, terms, False)
            else:
                f0, f1, f2, gain, row = _row_sums(dim, x, xi0, xi1, xi2, e0, e1, pair_j, terms, True)
        else:
            f0, f1, f2, gain, row, n_row, min_ratio2 = _whole_row(
                form, dim, x, xi0, xi1, xi2, di, e0, e1, pair_j, diam, pair_lambda, a3, a4, beta, lam_floor,
                clip, weighted_dual, update_lambda, min_ratio2)
            n_active += n_row
        # the container's walls (``kernels.walls``), each term as a pair's with the sphere's
        # own diameter as size: phi = c (d_i/2 - s), |grad phi|^2 = c^2, |Hess phi| = c / rho
        for wall in range(walls.shape[0]):
            s, n0, n1, n2, curv = walls_mod.gap(dim, walls, wall, xi0, xi1, xi2)
            phi, cw = walls_mod.wall_constraint(form == SMOOTH, di, s)
            g2 = cw * cw
            hess = cw * curv
            unit = 1.0
            if clip:
                unit = 1.0 / (di * di) if form == SMOOTH else 1.0 / di
            lam, m, gain_i, row_i = _term(wall_lambda[i, wall], phi, phi * unit, g2, hess, unit, a3, a4, beta,
                                          lam_floor, clip, weighted_dual, update_lambda)
            if update_lambda:
                wall_lambda[i, wall] = lam
            if phi > 0.0 and (0.5 * di - s) > wall_overlap * (0.5 * di):
                wall_overlap = (0.5 * di - s) / (0.5 * di)
            gain += gain_i
            if lam > 0.0:
                n_active += 2
            if m != 0.0:
                row += row_i
                g = m * cw  # m grad_i phi_iw = -g n_iw
                f0 -= g * n0
                f1 -= g * n1
                f2 -= g * n2
        row = a3 + 2.0 * row
        if gain > max_gain:
            max_gain = gain
        if row > max_row:
            max_row = row
        # G = -(a3 grad W + F), D = (a1 - 1) X^n + a2 X^{n-1} + G, per coordinate; grad W is
        # X_i - Xbar, or the sphere's weight under gravity (``kernels.potential``)
        p0, p1, p2 = potential.pull(dim, pot, di, xi0, xi1, xi2, xb0, xb1, xb2)
        if gravity:
            exactsum.put(cols, dim + ACC_WPOT, i, potential.height_energy(dim, pot, di, xi0, xi1, xi2))
        # (a gradient pass's a2 is 0: X^{n-1} is not read, a2 X^n adds the same zero)
        xp0 = xi0 if gradient_pass else x_prev[i, 0]
        dd0, dx2, xx2, power, force2 = _coordinate(a1, a2, a3, xi0, xp0, p0, f0)
        dd1 = 0.0
        dd2 = 0.0
        if dim > 1:
            dd1, s_dx, s_xx, s_pw, s_f = _coordinate(a1, a2, a3, xi1, xi1 if gradient_pass else x_prev[i, 1], p1, f1)
            dx2 += s_dx
            xx2 += s_xx
            power += s_pw
            force2 += s_f
        if dim > 2:
            dd2, s_dx, s_xx, s_pw, s_f = _coordinate(a1, a2, a3, xi2, xi2 if gradient_pass else x_prev[i, 2], p2, f2)
            dx2 += s_dx
            xx2 += s_xx
            power += s_pw
            force2 += s_f
        if vmax > 0.0 and dx2 > vmax * vmax:
            scale = vmax / np.sqrt(dx2)
            dd0 *= scale
            dd1 *= scale
            dd2 *= scale
            dx2 = vmax * vmax
        xn0 = xi0 + dd0
        x_new[i, 0] = xn0
        if dim > 1:
            xn1 = xi1 + dd1
            x_new[i, 1] = xn1
        if dim > 2:
            xn2 = xi2 + dd2
            x_new[i, 2] = xn2
        exactsum.put(cols, dim + ACC_XX2, i, xx2)
        if not gradient_pass:  # an L-BFGS gradient pass needs only |X^n|^2 of these
            exactsum.put(cols, 0, i, xn0)
            if dim > 1:
                exactsum.put(cols, 1, i, xn1)
            if dim > 2:
                exactsum.put(cols, 2, i, xn2)
            exactsum.put(cols, dim + ACC_DX2, i, dx2)
            exactsum.put(cols, dim + ACC_POWER, i, power)
            exactsum.put(cols, dim + ACC_FORCE2, i, force2)
        if exactsum.block_ends(i):
            exactsum.add_block(cols, acc)
        if dx2 > max_step2 or dx2 != dx2:
            max_step2 = dx2
    exactsum.flush_columns(cols, acc, n_local)
    maxima[MAX_STEP2] = max_step2
    max_overlap = 1.0 - np.sqrt(min_ratio2)
    if wall_overlap > max_overlap:
        max_overlap = wall_overlap
    maxima[MAX_OVERLAP] = max_overlap
    maxima[MAX_GAIN] = max_gain
    maxima[MAX_ROW] = max_row
    return n_active


_DOC = """One pass of the fire-al step for one form and dimension; see the module docstring.

    Arguments: (x, x_prev, x_new, n_local, diam, pair_offsets, pair_j, pair_lambda, pairs, walls,
    wall_lambda (``kernels.walls``; shape (0, 8) and (n_local, 0) without a container), xbar, pot
    (``kernels.potential``: grad W is X - xbar, or the weights under gravity, whose W / g is then
    summed into row b + ACC_WPOT of acc, in every pass),
    a1, a2, a3, a4, beta, lam_floor, clip, weighted_dual, vmax, update_lambda, acc, maxima,
    gradient_pass). gradient_pass True, L-BFGS's gradient pass (a1 = 1, a2 = 0): X^{n-1}
    is not read (x_prev may be x), of the exact sums only |X^n|^2, and of the maxima the gain
    and the row are not computed (0 and a3).
    Shapes as ``kernels.multipliers_and_step``; acc int64 (b+N_ACC, exactsum.NBINS+1), added to;
    maxima float64 (N_MAX,), overwritten. Returns the number of row entries with lambda > 0.
    pairs: (half_i, half_e, half_j, half_f, terms), the rows' half list and a terms buffer
    (b + 2, n_pairs), made with the rows (``pair_work``), or ``WHOLE_ROWS``.
    """


# error_model "numpy": no zero-division checks in the pair loop (every divisor is a diameter
# or a guarded distance); the results are the same bits
@njit(cache=True, error_model="numpy")
def fire_s1(x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad):
    return _fire_al_step(SMOOTH, 1, x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad)


@njit(cache=True, error_model="numpy")
def fire_s2(x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad):
    return _fire_al_step(SMOOTH, 2, x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad)


@njit(cache=True, error_model="numpy")
def fire_s3(x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad):
    return _fire_al_step(SMOOTH, 3, x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad)


@njit(cache=True, error_model="numpy")
def fire_ns1(x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad):
    return _fire_al_step(NONSMOOTH, 1, x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad)


@njit(cache=True, error_model="numpy")
def fire_ns2(x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad):
    return _fire_al_step(NONSMOOTH, 2, x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad)


@njit(cache=True, error_model="numpy")
def fire_ns3(x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad):
    return _fire_al_step(NONSMOOTH, 3, x, xp, xn, n, diam, po, pj, pl, pairs, wa, wl, xbar, pot, a1, a2, a3, a4, beta, fl, clip, wd, vmax, upd, acc, mx, grad)


_STEPS = {("S", 1): fire_s1, ("S", 2): fire_s2, ("S", 3): fire_s3,
          ("NS", 1): fire_ns1, ("NS", 2): fire_ns2, ("NS", 3): fire_ns3}
for _f in _STEPS.values():
    _f.__doc__ = _DOC


@njit(cache=True)
def pair_halves(n_local, pair_offsets, pair_j, pair_lambda, mirror):
    """Each pair of two local spheres once: the half list of the rows, for a pass that computes
    a pair's terms once and writes them to both of its entries (``_pair_terms``).

    mirror int64 (n_pairs,): each entry's mirror, the entry of the partner's row whose partner
    is this entry's sphere, or -1 (``neighbors.build_rows`` or ``neighbors.find_mirrors``).
    Returns (half_i int32, half_e int64, half_j int32, half_f int64, each (n_half,)): the
    listed entries half_e in row order, their spheres half_i (ascending), partners half_j and
    mirrors half_f, or -1. An entry is listed unless it is the mirror of one that is: of an
    entry pair (e of row i, f of row j) the one with i < j is listed, with mirror f; an entry
    whose partner is a ghost, or whose mirror is missing or holds another lambda (the pair's two
    entries must hold the same bits: every pass then keeps them so), is listed with mirror -1.
    """
    # every entry is written at the next free place, and kept (k advances) when listed
    n_pairs = pair_offsets[n_local]
    half_i = np.empty(n_pairs, dtype=np.int32)
    half_e = np.empty(n_pairs, dtype=np.int64)
    half_j = np.empty(n_pairs, dtype=np.int32)
    half_f = np.empty(n_pairs, dtype=np.int64)
    k = 0
    for i in range(n_local):
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            f = mirror[e]
            if f >= 0 and not pair_lambda[f] == pair_lambda[e]:
                f = -1
            half_i[k] = i
            half_e[k] = e
            half_j[k] = pair_j[e]
            half_f[k] = f
            k += np.int64(f < 0 or pair_j[e] > i)
    return half_i[:k].copy(), half_e[:k].copy(), half_j[:k].copy(), half_f[:k].copy()


# the pass walks whole rows, with no half list, when the rows hold more entries than this per
# sphere (a dense start's first pass: hundreds a sphere; a run's rows hold about 6 in 2D, 8 - 11
# in 3D): the half list's 24 + 8 (b + 2) bytes an entry would then outgrow the rows' own memory guard
HALF_LIST_MAX_ROW = 24

# the ``pairs`` of a pass that walks whole rows (no half list)
WHOLE_ROWS = (np.zeros(0, dtype=np.int32), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int32),
              np.zeros(0, dtype=np.int64), np.zeros((0, 0)))


def pair_work(dim, n_local, pair_offsets, pair_j, pair_lambda, mirror, max_row=HALF_LIST_MAX_ROW):
    """The ``pairs`` argument of a pass over these rows: (half_i, half_e, half_j, half_f)
    of ``pair_halves`` and a terms buffer (dim + 2, n_pairs), from the entries' mirrors as the
    rows' build found them (``neighbors.build_rows``); ``WHOLE_ROWS`` when the rows hold more
    than ``max_row`` entries a sphere, or when the build found no mirrors (mirror None: a dense
    start's rows, a rank near its memory limit, a gid twice; the pass's bits are the same)."""
    if mirror is None or pair_offsets[n_local] > max_row * n_local:
        return WHOLE_ROWS
    halves = pair_halves(n_local, pair_offsets, pair_j, pair_lambda, mirror)
    return halves + (np.empty((n_terms(dim), int(pair_offsets[n_local]))),)


def fire_al_step(form, dim):
    """The compiled fire-al kernel for a constraint form ('S' or 'NS') and dimension (1-3)."""
    return _STEPS[(form, dim)]
