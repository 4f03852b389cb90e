"""Geometric measures of a configuration (serial kernels, no MPI).

Packing density about a centre (paper, Figs. 8 and 10a): the measure of the union of the
spheres inside a ball B(centre, R) divided by the measure of B. Overlaps are negligible in a
converged packing, so the union is taken as the sum of the sphere-ball intersections.
"""

import math

from mpipack.jit import njit
from mpipack.parallel import exactsum


@njit(cache=True, inline="always")
def ball_volume(dim, a):
    """Measure of a ball of radius a: length (1D), area (2D), volume (3D)."""
    if dim == 1:
        return 2.0 * a
    if dim == 2:
        return math.pi * a * a
    return 4.0 / 3.0 * math.pi * a * a * a


@njit(cache=True, inline="always")
def intersection(dim, s, a, R):
    """Measure of B(p, a) ∩ B(0, R) with |p| = s: length (1D), area (2D), volume (3D)."""
    if s >= a + R:
        return 0.0
    if dim == 1:
        lo = max(s - a, -R)
        hi = min(s + a, R)
        return max(0.0, hi - lo)
    small = min(a, R)
    if s <= abs(R - a):
        if dim == 2:
            return math.pi * small * small
        return 4.0 / 3.0 * math.pi * small ** 3
    if dim == 2:
        # area of the lens of two discs
        c1 = (s * s + a * a - R * R) / (2.0 * s * a)
        c2 = (s * s + R * R - a * a) / (2.0 * s * R)
        c1 = min(1.0, max(-1.0, c1))
        c2 = min(1.0, max(-1.0, c2))
        k = (-s + a + R) * (s + a - R) * (s - a + R) * (s + a + R)
        return a * a * math.acos(c1) + R * R * math.acos(c2) - 0.5 * math.sqrt(max(0.0, k))
    # volume of the lens of two balls
    t = a + R - s
    return math.pi * t * t * (s * s + 2.0 * s * (a + R) - 3.0 * (a - R) ** 2) / (12.0 * s)


@njit(cache=True)
def covered_measure(x, diam, n_local, centre, radii, acc):
    """Exact sums over local spheres of |sphere ∩ B(centre, R)| for each R in radii (acc rows)."""
    dim = x.shape[1]
    fbuf = exactsum.staging(acc)
    for i in range(n_local):
        s2 = 0.0
        for k in range(dim):
            s2 += (x[i, k] - centre[k]) ** 2
        s = math.sqrt(s2)
        for q in range(radii.shape[0]):
            exactsum.add(fbuf, acc, q, intersection(dim, s, 0.5 * diam[i], radii[q]))
    exactsum.flush(fbuf, acc)


def ball_measure(dim, R):
    return {1: 2.0 * R, 2: math.pi * R * R, 3: 4.0 / 3.0 * math.pi * R ** 3}[dim]
