"""A container's walls as constraints per sphere. Serial array code: never imports MPI.

Each wall w gives every sphere i the signed distance s_iw = dist(X_i, wall), positive inside,
and the inward unit normal n_iw = grad_{X_i} s_iw. The sphere stays inside when its centre is
at least its radius from the wall:

    NS (non-smooth):  phi_iw = d_i/2 - s_iw,            grad_{X_i} phi_iw = -n_iw
    S  (smooth):      phi_iw = d_i (d_i/2 - s_iw),      grad_{X_i} phi_iw = -d_i n_iw

(S: the same constraint in the units of a pair's d_kl^2 - r^2; a plane's distance is linear, so
it needs no square), i.e. phi_iw = c_i (d_i/2 - s_iw) with c_i = 1 (NS) or d_i (S). Each has
its own multiplier lambda_iw >= 0, stored with the sphere (``State.wall_lambda``, (n_local,
n_walls)): walls are global geometry, so a wall term needs nothing from another rank. The
overlap of a sphere with a wall, as a pair's (d_kl - r)/d_kl with its mirror image, is
(d_i/2 - s_iw) / (d_i/2).

Walls are rows of a float64 array ``walls`` (n_walls, WALL_WIDTH):

    PLANE      [PLANE, n_0, n_1, n_2, o, 0, 0, 0]      s = n.X - o (n unit, inward)
    CYLINDER   [CYLINDER, c_0, c_1, c_2, R, k, 0, 0]   s = R - |X - c| over the axes other than k
    SPHERE     [SPHERE, c_0, c_1, c_2, R, 0, 0, 0]     s = R - |X - c|

(components beyond the dimension 0). The curvature 1/rho of a round wall (rho the centre's
distance from its axis or centre) bounds the Hessian of s, for the fire-al schedule's
Gershgorin row.
"""

import math

import numpy as np

from mpipack.jit import njit

PLANE, CYLINDER, SPHERE = 0.0, 1.0, 2.0
WALL_WIDTH = 8


def walls_of(container, dim):
    """The walls of a ``config.Container`` in ``dim`` dimensions: float64 (n_walls, WALL_WIDTH),
    shape (0, WALL_WIDTH) without a container."""
    rows = []
    pad = lambda v: list(v) + [0.0] * (3 - len(v))
    if container.kind == "box":
        for k in range(dim):
            n = [0.0, 0.0, 0.0]
            n[k] = 1.0
            rows.append([PLANE, *n, container.lo[k], 0.0, 0.0, 0.0])  # s = x_k - lo_k
            n = [0.0, 0.0, 0.0]
            n[k] = -1.0
            rows.append([PLANE, *n, -container.hi[k], 0.0, 0.0, 0.0])  # s = hi_k - x_k
    elif container.kind == "cylinder":
        c = pad(container.centre)
        rows.append([CYLINDER, *c, container.radius, 2.0, 0.0, 0.0])
        rows.append([PLANE, 0.0, 0.0, 1.0, c[2], 0.0, 0.0, 0.0])  # the floor
        if container.height is not None:
            rows.append([PLANE, 0.0, 0.0, -1.0, -(c[2] + container.height), 0.0, 0.0, 0.0])  # the lid
    elif container.kind == "sphere":
        rows.append([SPHERE, *pad(container.centre), container.radius, 0.0, 0.0, 0.0])
    return np.array(rows, dtype=np.float64).reshape(len(rows), WALL_WIDTH)


def wall_names(container, dim):
    """One short name per wall row of ``walls_of`` (for summaries and files)."""
    if container.kind == "box":
        return [f"{side}{'xyz'[k]}" for k in range(dim) for side in ("-", "+")]
    if container.kind == "cylinder":
        return ["side", "floor"] + (["lid"] if container.height is not None else [])
    if container.kind == "sphere":
        return ["sphere"]
    return []


@njit(cache=True, inline="always")
def gap(dim, walls, w, x0, x1, x2):
    """(s, n0, n1, n2, curvature) of a centre (x0, x1, x2) (0 beyond dim) and wall row w: the
    signed distance inside, the inward unit normal and 1/rho of a round wall (0 for a plane).
    A centre on a round wall's axis or centre has no normal: n = 0 there."""
    kind = walls[w, 0]
    if kind == PLANE:
        return (walls[w, 1] * x0 + walls[w, 2] * x1 + walls[w, 3] * x2 - walls[w, 4],
                walls[w, 1], walls[w, 2], walls[w, 3], 0.0)
    v0 = x0 - walls[w, 1]
    v1 = x1 - walls[w, 2] if dim > 1 else 0.0
    v2 = x2 - walls[w, 3] if dim > 2 else 0.0
    if kind == CYLINDER:
        axis = int(walls[w, 5])
        if axis == 0:
            v0 = 0.0
        elif axis == 1:
            v1 = 0.0
        else:
            v2 = 0.0
    rho = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if rho > 0.0:
        return walls[w, 4] - rho, -v0 / rho, -v1 / rho, -v2 / rho, 1.0 / rho
    return walls[w, 4], 0.0, 0.0, 0.0, 0.0


@njit(cache=True, inline="always")
def wall_constraint(smooth, di, s):
    """(phi_iw, c_i) of a sphere of diameter di at distance s inside a wall: phi = c (di/2 - s),
    grad phi = -c n, with c = di (S) or 1 (NS)."""
    c = di if smooth else 1.0
    return c * (0.5 * di - s), c


@njit(cache=True)
def max_outside(x, n_local, diam, walls):
    """The largest (d_i/2 - s_iw) / (d_i/2) over local spheres and walls (0 if none is beyond a
    wall): how far the worst sphere sticks out of the container, in radii."""
    dim = x.shape[1]
    worst = 0.0
    for i in range(n_local):
        x0 = x[i, 0]
        x1 = x[i, 1] if dim > 1 else 0.0
        x2 = x[i, 2] if dim > 2 else 0.0
        for w in range(walls.shape[0]):
            s, n0, n1, n2, curv = gap(dim, walls, w, x0, x1, x2)
            ov = (0.5 * diam[i] - s) / (0.5 * diam[i])
            if ov > worst:
                worst = ov
    return worst


def inside(x, diam, walls, margin=0.0):
    """Project centres x (m, b) into the container shrunk by d_i/2 (and ``margin``) along each
    wall's normal in turn, in place; used by the start (``engine.initial``) so that no sphere
    begins outside. Pure numpy, per sphere: the same on any rank count."""
    dim = x.shape[1]
    for w in range(walls.shape[0]):
        row = walls[w]
        full = np.zeros((x.shape[0], 3))
        full[:, :dim] = x
        if row[0] == PLANE:
            n = row[1:4]
            # element by element (a BLAS product may split the sum differently by length)
            s = full[:, 0] * n[0] + full[:, 1] * n[1] + full[:, 2] * n[2] - row[4]
            need = 0.5 * diam + margin
            short = np.maximum(need - s, 0.0)
            full += short[:, None] * n[None, :]
        else:
            v = full - row[1:4][None, :]
            if row[0] == CYLINDER:
                v[:, int(row[5])] = 0.0
            rho = np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])
            lim = row[4] - 0.5 * diam - margin
            over = rho > lim
            scale = np.where(over & (rho > 0), lim / np.where(rho > 0, rho, 1.0), 1.0)
            full -= v * (1.0 - scale)[:, None]
        x[:] = full[:, :dim]
    return x
