"""Numba kernels of the L-BFGS inner solver (``qn``): per-sphere vector work, no pairs, no MPI.

Per local sphere i the memory ``qn[i]`` (shape (K, b), K = 2m + 1) holds the sphere's pieces of
the slots S_0 .. S_{m-1}, Y_0 .. Y_{m-1}, G_OLD (see ``qn``). The current gradient
g_i = grad_i L_rho comes from the fire-al kernel run as a plain gradient pass (a1 = 1, a2 = 0,
a3 = 1, a4 = c_b, no speed cap), which writes X^n - g into x_new; it is read there.

    dots       exact sums of g.slot_j (S, Y, G_OLD), of g.g, of the positions X^n (b rows:
               the centre of mass) and of |S_head|^2 (the last step's length); the largest
               |S_head,i|^2 and the number of spheres whose last step was shortened to the cap
    direction  Y_{y_slot} = g - G_OLD (if y_slot >= 0); step_i = sum_j coef_j basis_j(i) over
               [S, Y, g], shortened to ``cap`` if longer; S_{s_slot} = step; G_OLD = g;
               X^{n+1} = X^n + step
    backtrack  a failed step s: S_{s_slot} = s/2, X^{n+1} = X^n - s/2 (half way from the
               previous X, whose gradient G_OLD keeps)
"""

import numpy as np
from numba import njit

from . import exactsum

# a stored step this close to the cap was shortened to it
_AT_CAP = 1.0 - 1e-9


@njit(cache=True, error_model="numpy")
def dots(x, x_new, n_local, qn, head, cap, acc, maxima):
    """acc rows: g.slot_j (j = 0 .. K-1), g.g, sum X^n (b rows), sum |S_head|^2; maxima[0]:
    max |S_head,i|^2 (head < 0: no last step, zeros). g_i = x_i - x_new_i. Returns the number
    of local spheres whose last step is at the cap."""
    fbuf = exactsum.staging(acc)
    k_slots = qn.shape[1]
    dim = x.shape[1]
    max2 = 0.0
    at_cap = 0
    g = np.empty(3)
    for i in range(n_local):
        gg = 0.0
        for c in range(dim):
            g[c] = x[i, c] - x_new[i, c]
            gg += g[c] * g[c]
        for j in range(k_slots):
            v = 0.0
            for c in range(dim):
                v += g[c] * qn[i, j, c]
            exactsum.add(fbuf, acc, j, v)
        exactsum.add(fbuf, acc, k_slots, gg)
        for c in range(dim):
            exactsum.add(fbuf, acc, k_slots + 1 + c, x[i, c])
        if head >= 0:
            s2 = 0.0
            for c in range(dim):
                s2 += qn[i, head, c] * qn[i, head, c]
            exactsum.add(fbuf, acc, k_slots + 1 + dim, s2)
            if s2 > max2 or s2 != s2:
                max2 = s2
            if s2 >= _AT_CAP * cap * cap:
                at_cap += 1
    exactsum.flush(fbuf, acc)
    maxima[0] = max2
    return at_cap


@njit(cache=True, error_model="numpy")
def direction(x, x_new, n_local, qn, coef, y_slot, s_slot, cap):
    """X^{n+1} = X^n + sum_j coef_j basis_j over [S, Y, g] (each sphere's move at most
    ``cap``) into x_new, which holds X^n - g on entry; updates the slots (module docstring)."""
    k_slots = qn.shape[1]
    g_old = k_slots - 1
    m = (k_slots - 1) // 2
    dim = x.shape[1]
    used = np.empty(k_slots, dtype=np.int64)  # the memory slots with a nonzero coefficient
    n_used = 0
    for j in range(k_slots - 1):
        if coef[j] != 0.0:
            used[n_used] = j
            n_used += 1
    cg = coef[k_slots - 1]  # the gradient's
    g = np.zeros(3)
    p = np.zeros(3)
    for i in range(n_local):
        for c in range(dim):
            g[c] = x[i, c] - x_new[i, c]
            if y_slot >= 0:
                qn[i, m + y_slot, c] = g[c] - qn[i, g_old, c]
            p[c] = cg * g[c]
        for u in range(n_used):
            j = used[u]
            w = coef[j]
            for c in range(dim):
                p[c] += w * qn[i, j, c]
        s2 = 0.0
        for c in range(dim):
            s2 += p[c] * p[c]
        if s2 > cap * cap:
            scale = cap / np.sqrt(s2)
            for c in range(dim):
                p[c] *= scale
        for c in range(dim):
            qn[i, s_slot, c] = p[c]
            qn[i, g_old, c] = g[c]
            x_new[i, c] = x[i, c] + p[c]


@njit(cache=True, error_model="numpy")
def backtrack(x, x_new, n_local, qn, s_slot):
    """The last step s (slot s_slot) failed: S_{s_slot} = s/2 and X^{n+1} = X^n - s/2, the
    point half way along it from the same X; G_OLD stays that X's gradient."""
    dim = x.shape[1]
    for i in range(n_local):
        for c in range(dim):
            half = 0.5 * qn[i, s_slot, c]
            qn[i, s_slot, c] = half
            x_new[i, c] = x[i, c] - half
