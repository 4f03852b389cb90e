"""Numba kernels of the L-BFGS inner solver (``qn``): per-sphere vector work, no pairs, no MPI.

Per local sphere i the memory ``qn[i]`` (shape (K, b), K = 2m + 1) holds the sphere's pieces of
the slots S_0 .. S_{m-1}, Y_0 .. Y_{m-1}, G_OLD (see ``qn``). The current gradient
g_i = grad_i L_rho comes from the fire-al kernel run as a plain gradient pass (a1 = 1, a2 = 0,
a3 = 1, a4 = c_b, no speed cap), which writes X^n - g into x_new; it is read there.

    dots       exact sums of g.slot_j (S, Y, G_OLD), of g.g, of the positions X^n (b rows:
               the centre of mass), of |S_head|^2 (the last step's length) and of
               G_OLD.S_head (the last step's slope where it began: with g.S_head, the
               descent test of a shortened step, whose B row is not the step taken); the largest
               |S_head,i|^2 and the number of spheres whose last step was shortened to the cap
    direction  Y_{y_slot} = g - G_OLD (if y_slot >= 0); step_i = sum_j coef_j basis_j(i) over
               [S, Y, g], shortened to ``cap`` if longer; S_{s_slot} = step; G_OLD = g;
               X^{n+1} = X^n + step
    backtrack  a failed step s: S_{s_slot} = s/2, X^{n+1} = X^n - s/2 (half way from the
               previous X, whose gradient G_OLD keeps)

Each is written once for a compile-time dimension (``_dots(dim, ...)`` inlined into one small
wrapper per dimension, as in ``kernels``): a sphere's g and step then live in registers. The
first version looped over a runtime ``range(dim)`` through small temporary arrays, and its
direction pass cost about three times as much (1.92 ms against 0.67 ms for 50000 spheres, m = 5,
2D, an idle machine); the arithmetic and its order are the same, so are the bits. ``dots``
puts its 2m + 4 + b values per sphere into the exact sums' columns (``exactsum.columns``: cut
and summed a block of spheres at a time, in vector instructions), the same accumulator bit for
bit as per-value adds (docs/benchmarks.md, "Exact sums by columns").
"""

import numpy as np

from mpipack.jit import njit
from mpipack.parallel import exactsum

# a stored step this close to the cap was shortened to it
_AT_CAP = 1.0 - 1e-9

# The run's number of slots (``methods.lbfgs.MEMORY`` = 5 pairs in every dimension: 2m + 1):
# compiled with it as a constant, the loops over the slots are unrolled, the same arithmetic in
# the same order (about a fifth faster: docs/benchmarks.md, session 40). Another memory takes
# the kernels compiled for any number of slots.
UNROLLED_SLOTS = 11


@njit(cache=True, inline="always")
def _dots(dim, fixed_slots, x, x_new, n_local, qn, head, cap, acc, maxima):
    # fixed_slots: the slots as a compile-time constant (UNROLLED_SLOTS), or 0: qn's
    k_slots = fixed_slots if fixed_slots > 0 else qn.shape[1]
    # one value per accumulator row and sphere, summed down the rows' columns a block of
    # spheres at a time (``exactsum.columns``)
    cols = exactsum.columns(acc)
    max2 = 0.0
    at_cap = 0
    for i in range(n_local):
        # g_i = X^n_i - (X^n_i - g_i), as the gradient pass left it
        g0 = x[i, 0] - x_new[i, 0]
        g1 = x[i, 1] - x_new[i, 1] if dim > 1 else 0.0
        g2 = x[i, 2] - x_new[i, 2] if dim > 2 else 0.0
        gg = 0.0
        gg += g0 * g0
        if dim > 1:
            gg += g1 * g1
        if dim > 2:
            gg += g2 * g2
        for j in range(k_slots):
            s = 0.0
            s += g0 * qn[i, j, 0]
            if dim > 1:
                s += g1 * qn[i, j, 1]
            if dim > 2:
                s += g2 * qn[i, j, 2]
            exactsum.put(cols, j, i, s)
        exactsum.put(cols, k_slots, i, gg)
        exactsum.put(cols, k_slots + 1, i, x[i, 0])
        if dim > 1:
            exactsum.put(cols, k_slots + 2, i, x[i, 1])
        if dim > 2:
            exactsum.put(cols, k_slots + 3, i, x[i, 2])
        if head >= 0:  # else the rows of |S_head|^2 and G_OLD.S_head get zeros
            s2 = 0.0
            s2 += qn[i, head, 0] * qn[i, head, 0]
            if dim > 1:
                s2 += qn[i, head, 1] * qn[i, head, 1]
            if dim > 2:
                s2 += qn[i, head, 2] * qn[i, head, 2]
            exactsum.put(cols, k_slots + 1 + dim, i, s2)
            # G_OLD.S_head: the slope of the step actually taken (shortened or not) at its start
            gs = 0.0
            gs += qn[i, k_slots - 1, 0] * qn[i, head, 0]
            if dim > 1:
                gs += qn[i, k_slots - 1, 1] * qn[i, head, 1]
            if dim > 2:
                gs += qn[i, k_slots - 1, 2] * qn[i, head, 2]
            exactsum.put(cols, k_slots + 2 + dim, i, gs)
            if s2 > max2 or s2 != s2:
                max2 = s2
            if s2 >= _AT_CAP * cap * cap:
                at_cap += 1
        if exactsum.block_ends(i):
            exactsum.add_block(cols, acc)
    exactsum.flush_columns(cols, acc, n_local)
    maxima[0] = max2
    return at_cap


@njit(cache=True, inline="always")
def _direction(dim, fixed_slots, x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    k_slots = fixed_slots if fixed_slots > 0 else qn.shape[1]
    used = np.empty(k_slots, dtype=np.int64)  # the memory slots with a nonzero coefficient
    n_used = 0
    for j in range(k_slots - 1):
        if coef[j] != 0.0:
            used[n_used] = j
            n_used += 1
    all_used = n_used == k_slots - 1  # (the memory is full: every slot counts)
    if fixed_slots > 0 and all_used:  # every slot, a constant number of them: unrolled
        _moves(dim, k_slots, fixed_slots - 1, used, True, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)
    else:
        _moves(dim, k_slots, n_used, used, all_used, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


@njit(cache=True, inline="always")
def _moves(dim, k_slots, n_used, used, all_used, x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    """``_direction``'s pass over the spheres, with the slots used[:n_used] (slots 0 ..
    n_used - 1 if all_used: the index array's look-up skipped, ~30% faster, the same adds)."""
    g_old = k_slots - 1
    m = (k_slots - 1) // 2
    cg = coef[k_slots - 1]  # the gradient's
    for i in range(n_local):
        g0 = x[i, 0] - x_new[i, 0]
        g1 = x[i, 1] - x_new[i, 1] if dim > 1 else 0.0
        g2 = x[i, 2] - x_new[i, 2] if dim > 2 else 0.0
        if y_slot >= 0:
            qn[i, m + y_slot, 0] = g0 - qn[i, g_old, 0]
            if dim > 1:
                qn[i, m + y_slot, 1] = g1 - qn[i, g_old, 1]
            if dim > 2:
                qn[i, m + y_slot, 2] = g2 - qn[i, g_old, 2]
        p0 = cg * g0
        p1 = cg * g1
        p2 = cg * g2
        for u in range(n_used):
            j = u if all_used else used[u]
            w = coef[j]
            p0 += w * qn[i, j, 0]
            if dim > 1:
                p1 += w * qn[i, j, 1]
            if dim > 2:
                p2 += w * qn[i, j, 2]
        s2 = 0.0
        s2 += p0 * p0
        if dim > 1:
            s2 += p1 * p1
        if dim > 2:
            s2 += p2 * p2
        if s2 > cap * cap:
            scale = cap / np.sqrt(s2)
            p0 *= scale
            p1 *= scale
            p2 *= scale
        qn[i, s_slot, 0] = p0
        qn[i, g_old, 0] = g0
        x_new[i, 0] = x[i, 0] + p0
        if dim > 1:
            qn[i, s_slot, 1] = p1
            qn[i, g_old, 1] = g1
            x_new[i, 1] = x[i, 1] + p1
        if dim > 2:
            qn[i, s_slot, 2] = p2
            qn[i, g_old, 2] = g2
            x_new[i, 2] = x[i, 2] + p2


@njit(cache=True, inline="always")
def _backtrack(dim, x, x_new, n_local, qn, s_slot):
    for i in range(n_local):
        half = 0.5 * qn[i, s_slot, 0]
        qn[i, s_slot, 0] = half
        x_new[i, 0] = x[i, 0] - half
        if dim > 1:
            half = 0.5 * qn[i, s_slot, 1]
            qn[i, s_slot, 1] = half
            x_new[i, 1] = x[i, 1] - half
        if dim > 2:
            half = 0.5 * qn[i, s_slot, 2]
            qn[i, s_slot, 2] = half
            x_new[i, 2] = x[i, 2] - half


# One small wrapper per dimension, and per dimension with UNROLLED_SLOTS, so that only what a
# scene uses is compiled (and cached); written out because numba caches top-level functions only.
@njit(cache=True, error_model="numpy")
def _dots1(x, x_new, n_local, qn, head, cap, acc, maxima):
    return _dots(1, 0, x, x_new, n_local, qn, head, cap, acc, maxima)


@njit(cache=True, error_model="numpy")
def _dots2(x, x_new, n_local, qn, head, cap, acc, maxima):
    return _dots(2, 0, x, x_new, n_local, qn, head, cap, acc, maxima)


@njit(cache=True, error_model="numpy")
def _dots3(x, x_new, n_local, qn, head, cap, acc, maxima):
    return _dots(3, 0, x, x_new, n_local, qn, head, cap, acc, maxima)


@njit(cache=True, error_model="numpy")
def _dots1_unrolled(x, x_new, n_local, qn, head, cap, acc, maxima):
    return _dots(1, UNROLLED_SLOTS, x, x_new, n_local, qn, head, cap, acc, maxima)


@njit(cache=True, error_model="numpy")
def _dots2_unrolled(x, x_new, n_local, qn, head, cap, acc, maxima):
    return _dots(2, UNROLLED_SLOTS, x, x_new, n_local, qn, head, cap, acc, maxima)


@njit(cache=True, error_model="numpy")
def _dots3_unrolled(x, x_new, n_local, qn, head, cap, acc, maxima):
    return _dots(3, UNROLLED_SLOTS, x, x_new, n_local, qn, head, cap, acc, maxima)


@njit(cache=True, error_model="numpy")
def _direction1(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    _direction(1, 0, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


@njit(cache=True, error_model="numpy")
def _direction2(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    _direction(2, 0, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


@njit(cache=True, error_model="numpy")
def _direction3(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    _direction(3, 0, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


@njit(cache=True, error_model="numpy")
def _direction1_unrolled(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    _direction(1, UNROLLED_SLOTS, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


@njit(cache=True, error_model="numpy")
def _direction2_unrolled(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    _direction(2, UNROLLED_SLOTS, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


@njit(cache=True, error_model="numpy")
def _direction3_unrolled(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    _direction(3, UNROLLED_SLOTS, x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


@njit(cache=True, error_model="numpy")
def _backtrack1(x, x_new, n_local, qn, s_slot):
    _backtrack(1, x, x_new, n_local, qn, s_slot)


@njit(cache=True, error_model="numpy")
def _backtrack2(x, x_new, n_local, qn, s_slot):
    _backtrack(2, x, x_new, n_local, qn, s_slot)


@njit(cache=True, error_model="numpy")
def _backtrack3(x, x_new, n_local, qn, s_slot):
    _backtrack(3, x, x_new, n_local, qn, s_slot)


# by (dimension, unrolled)
_DOTS = {(1, False): _dots1, (2, False): _dots2, (3, False): _dots3,
         (1, True): _dots1_unrolled, (2, True): _dots2_unrolled, (3, True): _dots3_unrolled}
_DIRECTION = {(1, False): _direction1, (2, False): _direction2, (3, False): _direction3,
              (1, True): _direction1_unrolled, (2, True): _direction2_unrolled, (3, True): _direction3_unrolled}
_BACKTRACK = {1: _backtrack1, 2: _backtrack2, 3: _backtrack3}


def _unrolled(qn):
    return qn.shape[1] == UNROLLED_SLOTS


def dots(x, x_new, n_local, qn, head, cap, acc, maxima):
    """acc rows: g.slot_j (j = 0 .. K-1), g.g, sum X^n (b rows), sum |S_head|^2, sum
    G_OLD.S_head (the old gradient's slope along the step as taken, shortened or not); maxima[0]:
    max |S_head,i|^2 (head < 0: no last step, zeros). g_i = x_i - x_new_i. Returns the number
    of local spheres whose last step is at the cap. Shapes: x, x_new (n_total, b); qn
    (n_local, K, b); acc int64 (K + 1 + b + 2, exactsum.NBINS + 1), added to."""
    return _DOTS[x.shape[1], _unrolled(qn)](x, x_new, n_local, qn, head, cap, acc, maxima)


def direction(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    """X^{n+1} = X^n + sum_j coef_j basis_j over [S, Y, g] (each sphere's move at most
    ``cap``) into x_new, which holds X^n - g on entry; updates the slots (module docstring).
    coef (K,): the basis's coefficients, the gradient's last."""
    _DIRECTION[x.shape[1], _unrolled(qn)](x, x_new, n_local, qn, coef, y_slot, s_slot, cap)


def backtrack(x, x_new, n_local, qn, s_slot):
    """The last step s (slot s_slot) failed: S_{s_slot} = s/2 and X^{n+1} = X^n - s/2, the
    point half way along it from the same X; G_OLD stays that X's gradient."""
    _BACKTRACK[x.shape[1]](x, x_new, n_local, qn, s_slot)
