"""The gradient of W per sphere for each ``potential.kind``. Serial array code: never imports MPI.

    centre, point   grad_{X_i} W = X_i - A      (A = Xbar, or the fixed point P: the kernels'
                                                 ``xbar`` argument)
    gravity         grad_{X_i} W = m_i g e_b    W = g sum_i m_i (h_i - h_0), h = X_{i,b}, the
                                                 last coordinate (up), h_0 the container's bottom,
                                                 m_i = (d_i / d_mean)^b

The kernels take the potential as ``pot`` = [GRAVITY or 0, g, 1 / d_mean, h_0] (``parameters``)
and the centre's A as ``xbar``; under gravity xbar is not read. W of gravity is an exact sum of
m_i (h_i - h_0) (the kernels add it to the row after their own sums).
"""

import numpy as np

from mpipack.jit import njit
from mpipack.parallel import exactsum

GRAVITY = 1.0
POT_KIND, POT_G, POT_INV_D, POT_H0 = 0, 1, 2, 3


def parameters(scene):
    """``pot`` of a ``config.Scene``: float64 (4,)."""
    pot = scene.potential
    if pot.kind != "gravity":
        return np.zeros(4)
    return np.array([GRAVITY, float(pot.g), 1.0 / scene.particles.d_mean,
                     float(scene.container.bottom(scene.dim))])


@njit(cache=True, inline="always")
def mass(dim, pot, di):
    """m_i = (d_i / d_mean)^b, by multiplications (the same bits on every rank)."""
    r = di * pot[POT_INV_D]
    if dim == 1:
        return r
    if dim == 2:
        return r * r
    return r * r * r


@njit(cache=True, inline="always")
def pull(dim, pot, di, xi0, xi1, xi2, xb0, xb1, xb2):
    """grad_{X_i} W as three scalars (0 beyond dim): X_i - A, or m_i g along the last axis."""
    if pot[POT_KIND] == GRAVITY:
        w = mass(dim, pot, di) * pot[POT_G]
        if dim == 1:
            return w, 0.0, 0.0
        if dim == 2:
            return 0.0, w, 0.0
        return 0.0, 0.0, w
    return xi0 - xb0, xi1 - xb1, xi2 - xb2


@njit(cache=True, inline="always")
def height_energy(dim, pot, di, xi0, xi1, xi2):
    """m_i (h_i - h_0): sphere i's share of W / g under gravity."""
    h = xi0 if dim == 1 else (xi1 if dim == 2 else xi2)
    return mass(dim, pot, di) * (h - pot[POT_H0])


@njit(cache=True)
def gravity_sums(x, diam, n_local, pot, acc):
    """Exact sums over local spheres: row 0 sum_i m_i (h_i - h_0) (W / g), row 1 sum_i m_i^2
    (|grad W|^2 / g^2)."""
    dim = x.shape[1]
    fbuf = exactsum.staging(acc)
    for i in range(n_local):
        x0 = x[i, 0]
        x1 = x[i, 1] if dim > 1 else 0.0
        x2 = x[i, 2] if dim > 2 else 0.0
        m = mass(dim, pot, diam[i])
        exactsum.add(fbuf, acc, 0, height_energy(dim, pot, diam[i], x0, x1, x2))
        exactsum.add(fbuf, acc, 1, m * m)
    exactsum.flush(fbuf, acc)
