"""Initial configurations as pure functions of (seed, global id): independent of the partition.

Each rank generates the contiguous gid range it is given; the numbers for gid g are the same
whichever rank makes them, because they come from a counter-based generator (SplitMix64 of
seed, gid and a stream number), not from a sequential random stream.
"""

import math

import numpy as np

from mpipack.jit import njit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


@njit(cache=True, inline="always")
def _splitmix64(z):
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True, inline="always")
def draw64(seed, gid, stream):
    """64 random bits (uint64) from (seed, gid, stream)."""
    z = _splitmix64(np.uint64(seed) * np.uint64(0x100000001B3) + np.uint64(stream))
    return _splitmix64(z ^ (np.uint64(gid) * np.uint64(0xD6E8FEB86659FD93)))


@njit(cache=True, inline="always")
def uniform(seed, gid, stream):
    """Uniform in (0, 1) from (seed, gid, stream); 53 random bits."""
    z = draw64(seed, gid, stream)
    return (np.float64(z >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@njit(cache=True)
def gaussian(seed, gids, dim, sigma, centre):
    """x[i] ~ N(centre, sigma^2 I) for each gid (Box-Muller on counter-based uniforms)."""
    n = gids.shape[0]
    x = np.empty((n, dim))
    for i in range(n):
        g = gids[i]
        for k in range(0, dim, 2):
            u1 = uniform(seed, g, 2 * k)
            u2 = uniform(seed, g, 2 * k + 1)
            rad = math.sqrt(-2.0 * math.log(u1))
            x[i, k] = centre[k] + sigma * rad * math.cos(2.0 * math.pi * u2)
            if k + 1 < dim:
                x[i, k + 1] = centre[k + 1] + sigma * rad * math.sin(2.0 * math.pi * u2)
    return x


@njit(cache=True)
def diameters(seed, gids, d_min, d_max):
    """Diameters uniform in [d_min, d_max] per gid (all equal when d_min == d_max)."""
    n = gids.shape[0]
    d = np.empty(n)
    for i in range(n):
        if d_max > d_min:
            d[i] = d_min + (d_max - d_min) * uniform(seed, gids[i], 1000)
        else:
            d[i] = d_min
    return d


def lattice_points(n, dim, spacing):
    """The n points of a close-packed lattice nearest to the origin, ordered by distance.

    1D: a chain; 2D: triangular lattice; 3D: face-centred cubic; nearest-neighbour distance
    ``spacing``. Ties in distance are broken by coordinates, so the order (and so the gid of
    each point) is deterministic.
    """
    if dim == 1:
        cell = np.array([1.0])
        basis = np.array([[0.0]])
    elif dim == 2:
        cell = np.array([1.0, math.sqrt(3)])
        basis = np.array([[0.0, 0.0], [0.5, math.sqrt(3) / 2]])
    else:
        a = math.sqrt(2)
        cell = np.array([a, a, a])
        basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) * a
    per_cell = basis.shape[0]
    density = per_cell / float(np.prod(cell))
    vol_unit = {1: 2.0, 2: math.pi, 3: 4 * math.pi / 3}[dim]
    r = (n / (density * vol_unit)) ** (1.0 / dim) * 1.05 + 2
    m = [int(math.ceil(r / cell[k])) + 1 for k in range(dim)]
    axes = [np.arange(-m[k], m[k] + 1, dtype=np.float64) * cell[k] for k in range(dim)]
    grids = np.meshgrid(*axes, indexing="ij")
    corners = np.stack([g.ravel() for g in grids], axis=1)
    pts = (corners[:, None, :] + basis[None, :, :]).reshape(-1, dim)
    r2 = (pts ** 2).sum(axis=1)
    pts = pts[r2 <= (r + 1) ** 2]
    r2 = np.round((pts ** 2).sum(axis=1), 9)
    keys = [pts[:, k] for k in reversed(range(dim))] + [r2]
    order = np.lexsort(keys)
    if order.shape[0] < n:
        raise RuntimeError("lattice generation: not enough points")
    return pts[order[:n]] * spacing


@njit(cache=True)
def uniform_ball(seed, gids, dim, radius):
    """x[i] uniform in the ball B(0, radius) for each gid: a Gaussian direction and a radius
    radius * u^(1/dim), from counter-based uniforms (streams 10..15)."""
    n = gids.shape[0]
    x = np.empty((n, dim))
    e = np.empty(dim + 1)
    for i in range(n):
        g = gids[i]
        for k in range(0, dim, 2):
            u1 = uniform(seed, g, 10 + k)
            u2 = uniform(seed, g, 11 + k)
            rad = math.sqrt(-2.0 * math.log(u1))
            e[k] = rad * math.cos(2.0 * math.pi * u2)
            e[k + 1] = rad * math.sin(2.0 * math.pi * u2)
        norm = 0.0
        for k in range(dim):
            norm += e[k] * e[k]
        norm = math.sqrt(norm)
        r = radius * uniform(seed, g, 15) ** (1.0 / dim)
        for k in range(dim):
            x[i, k] = r * e[k] / norm
    return x


def unit_ball_measure(dim):
    return {1: 2.0, 2: math.pi, 3: 4.0 * math.pi / 3.0}[dim]


def mean_diameter(scene):
    """``scene.particles.d_mean``."""
    return scene.particles.d_mean


def gaussian_sigma(scene):
    """init.sigma, or for "auto" the spread that keeps the peak density of the paper's N = 2000
    start (standard Gaussian, unit diameters) at any N: sigma = d_mean (N / 2000)^(1/b)."""
    if scene.init.sigma != "auto":
        return float(scene.init.sigma)
    return mean_diameter(scene) * (scene.n / 2000.0) ** (1.0 / scene.dim)


def ball_radius(scene):
    """Radius of the ball whose packing fraction is init.fraction: N spheres of the mean
    volume, sum of sphere measures = fraction * ball measure."""
    mean_rb = scene.particles.mean_radius_power(scene.dim)
    return (scene.n * mean_rb / scene.init.fraction) ** (1.0 / scene.dim)


def positions(scene, gids):
    """Initial positions of the given gids for the scene's init block, shape (len(gids), dim).

    gaussian  N(0, sigma^2 I), sigma = init.sigma or "auto" (``gaussian_sigma``)
    ball      uniform in the ball of packing fraction init.fraction (``ball_radius``)
    lattice   the N points of a close-packed lattice nearest the origin, spacing
              init.spacing, plus a Gaussian jitter of std init.jitter
    file      row gid of init.file (``start_file``)
    """
    init = scene.init
    dim = scene.dim
    if init.kind == "file":
        return np.array(start_file(scene).x[gids], dtype=np.float64)
    if init.kind == "gaussian":
        return gaussian(scene.seed, gids, dim, gaussian_sigma(scene), np.zeros(dim))
    if init.kind == "ball":
        return uniform_ball(scene.seed, gids, dim, ball_radius(scene))
    if init.kind == "lattice":
        pts = lattice_points(scene.n, dim, float(init.spacing))
        x = pts[gids]
        if init.jitter > 0:
            x = x + gaussian(scene.seed, gids, dim, float(init.jitter), np.zeros(dim))
        return x
    raise ValueError(f"unknown init kind {init.kind!r}")


@njit(cache=True)
def uniforms(seed, gids, stream):
    """uniform(seed, gid, stream) of each gid, shape (len(gids),)."""
    u = np.empty(gids.shape[0])
    for i in range(gids.shape[0]):
        u[i] = uniform(seed, gids[i], stream)
    return u


def start_file(scene):
    """The ``io.start.Start`` of the scene's init.file, the numbers the scene was validated with
    (SceneError, one line, if the file changed since)."""
    from mpipack.io import start
    return _checked(scene.init.sha256, "init.file", scene.init.file,
                    lambda: start.read_start(scene.init.file, scene.dim, scene.init.iteration))


def diameters_file(scene):
    """The ``io.start.Start`` of the scene's particles.file (as ``start_file``)."""
    from mpipack.io import start
    return _checked(scene.particles.sha256, "particles.file", scene.particles.file,
                    lambda: start.read_diameters(scene.particles.file))


def _checked(sha256, key, path, read):
    from mpipack import config
    from mpipack.io import start
    try:
        got = read()
    except start.StartError as e:
        raise config.SceneError(f"key '{key}': {e}") from None
    if got.sha256 != sha256:
        raise config.SceneError(f"key '{key}': {path} changed since the scene was loaded "
                                f"(sha256 {got.sha256[:12]}..., loaded {str(sha256)[:12]}...)")
    return got


_FILE_ROW_STREAM = 1001  # the row of a diameters file whose row count is not N


@njit(cache=True)
def file_rows(seed, gids, rows):
    """The row of a diameters file of ``rows`` rows each gid takes: draw64(seed, gid) mod rows
    (the bias of the modulo, rows / 2^64, is nil for any file a run can read)."""
    out = np.empty(gids.shape[0], dtype=np.int64)
    r = np.uint64(rows)
    for i in range(gids.shape[0]):
        out[i] = np.int64(draw64(seed, gids[i], _FILE_ROW_STREAM) % r)
    return out


def scene_diameters(scene, gids):
    """Diameters of the given gids for the scene's particles block (``config.Particles``): each
    a function of (seed, gid), the same on any number of ranks."""
    from mpipack import config
    p = scene.particles
    gids = np.asarray(gids, dtype=np.int64)
    if p.distribution == "file":
        if scene.init.kind == "file":  # the start file's own diameters, row = gid
            return np.array(start_file(scene).diam[gids], dtype=np.float64)
        d = diameters_file(scene).diam
        if d.shape[0] == scene.n:
            return np.array(d[gids], dtype=np.float64)
        return np.array(d[file_rows(scene.seed, gids, d.shape[0])], dtype=np.float64)
    if p.distribution in ("uniform", "mono"):
        return diameters(scene.seed, gids, float(p.diameter), float(p.d_max))
    if p.distribution == "discrete":
        cum = np.cumsum(p.fractions) / float(np.sum(p.fractions))
        bounds = np.rint(scene.n * cum).astype(np.int64)   # gids [bounds[k-1], bounds[k]) have size k
        bounds[-1] = scene.n
        return np.asarray(p.sizes, dtype=np.float64)[np.searchsorted(bounds, gids, side="right")]
    from scipy.special import ndtr, ndtri
    # a standard normal truncated to |z| <= TRUNCATION, by the inverse of its distribution function
    lo, hi = ndtr(-config.TRUNCATION), ndtr(config.TRUNCATION)
    z = ndtri(lo + (hi - lo) * uniforms(scene.seed, gids, 1000))
    return config.truncated_diameters(p.distribution, float(p.diameter), float(p.spread), z)


# ---- a dense start ----------------------------------------------------------------------------
# A start whose spheres fill the uniform ball of their cloud's radius of gyration R_g more than
# DENSE_START times over (sum_i (d_i/2)^b > DENSE_START R^b, R^2 = (b+2)/b R_g^2: a packing
# measures at most ~1.15, a short chain of touching spheres; the default scene's Gaussian start
# hundreds) has its first pair rows built with the skin DENSE_START_SKIN (in largest diameters)
# instead of the usual one (``Solver.initialise``): they last only until the spread (its first
# pass moves the spheres by ~1e-3 d), and at the usual skin they are the run's largest.
DENSE_START = 2.0
DENSE_START_SKIN = 0.05


def is_dense(n, dim, sum_rb, radius2):
    """Whether n spheres of sum_i (d_i/2)^b = ``sum_rb`` are a dense start in a cloud of
    squared radius ``radius2`` (the uniform ball of its radius of gyration; see DENSE_START)."""
    return n > 1 and radius2 > 0.0 and sum_rb > DENSE_START * radius2 ** (0.5 * dim)


# ---- breaking an exact symmetry ---------------------------------------------------------------
# Spheres whose centres coincide exactly feel no force from each other: the S gradient
# -2 (X_i - X_j) is zero and the NS direction is undefined. A start (or a state read back)
# with such pairs is moved apart by a displacement of ``SEPARATION`` times the largest diameter
# in a direction drawn from (seed, gid): the same on any number of ranks.
SEPARATION = 1e-6
_SEPARATE_STREAM = 3000


@njit(cache=True)
def coincident_centres(x, n_local, pair_offsets, pair_j, flags):
    """flags[i] = True for local particles with a pair partner at exactly the same centre;
    returns how many."""
    count = 0
    b = x.shape[1]
    for i in range(n_local):
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            j = pair_j[e]
            same = True
            for k in range(b):
                if x[i, k] != x[j, k]:
                    same = False
                    break
            if same:
                flags[i] = True
                count += 1
                break
    return count


@njit(cache=True)
def separate(seed, gids, x, x_prev, flags, length):
    """Move each flagged particle (and its previous position: no momentum) by ``length`` in a
    unit direction from (seed, gid)."""
    b = x.shape[1]
    u = np.empty(b)
    for i in range(flags.shape[0]):
        if not flags[i]:
            continue
        norm = 0.0
        for k in range(b):
            u[k] = 2.0 * uniform(seed, gids[i], _SEPARATE_STREAM + k) - 1.0
            norm += u[k] * u[k]
        norm = np.sqrt(norm)
        for k in range(b):
            x[i, k] += length * u[k] / norm
            x_prev[i, k] += length * u[k] / norm


# ---- radial equalisation of a dense start (the fire-al schedule's first step) -------------------
EQUALISE_BINS = 4096


def radial_histogram(x, n_local, centre, r_max, bins=EQUALISE_BINS):
    """Counts of |X_i - centre| over ``bins`` equal bins of [0, r_max] (int64, shape (bins,)):
    summed over ranks, an exact (integer) picture of the cloud's radial distribution."""
    r = np.sqrt(((x[:n_local] - centre) ** 2).sum(axis=1))
    idx = np.minimum((r / r_max * bins).astype(np.int64), bins - 1) if r_max > 0 else np.zeros(n_local, np.int64)
    return np.bincount(idx, minlength=bins).astype(np.int64)


def equalise_radially(x, n_local, centre, r_max, counts, radius, dim):
    """Move every local centre along its ray from ``centre`` so that the cloud becomes a uniform
    ball of the given radius, keeping each particle's direction and the order of the radii:

        r -> radius F(r)^(1/b),   F the cloud's radial distribution function (``counts``,
                                  from ``radial_histogram`` summed over all ranks; linear
                                  within a bin)

    A Gaussian start has tails far beyond its bulk (the farthest of N at sqrt(2 ln N) sigma): a
    homothety that makes its core dilute puts its tail tens of radii out. x (n_total, b) is
    changed in place for the first n_local rows."""
    bins = counts.shape[0]
    n = counts.sum()
    if n == 0 or r_max <= 0:
        return
    cdf = np.concatenate(([0], np.cumsum(counts))).astype(np.float64) / n  # at bin edges
    d = x[:n_local] - centre
    r = np.sqrt((d * d).sum(axis=1))
    pos = np.minimum(r / r_max * bins, bins)
    k = np.minimum(pos.astype(np.int64), bins - 1)
    f = cdf[k] + (pos - k) * (cdf[k + 1] - cdf[k])
    scale = np.where(r > 0, radius * f ** (1.0 / dim) / np.where(r > 0, r, 1.0), 1.0)
    x[:n_local] = centre + d * scale[:, None]


def contain(scene, x, diam):
    """Start positions x (m, b) placed where the scene wants them, in place: a start drawn about
    the origin (gaussian, ball, lattice) moved to the container's middle or, without one, to
    the point W pulls to (potential.kind = "point"); then every centre projected inside the
    container by its radius (``kernels.walls.inside``): no sphere begins beyond a wall. Per
    sphere, so the same on any rank count. The paper's scenes are returned unchanged."""
    c, drawn = scene.container, scene.init.kind != "file"
    if not c.active:
        if drawn and scene.potential.kind == "point":
            x += np.asarray(scene.potential.point, dtype=np.float64)[None, :]
        return x
    from mpipack.kernels import walls
    if drawn:
        x += np.asarray(c.middle(scene.dim), dtype=np.float64)[None, :]
    return walls.inside(x, diam, walls.walls_of(c, scene.dim))


def fill_container(scene, gids, diam):
    """Positions uniform in the scene's container, each sphere's centre at least its radius
    inside (an open cylinder up to twice its radius or its bed, whichever is taller), from
    (seed, gid) (streams 10..19: the same on any rank count): the schedule's step 0 in a
    container (``methods.fire_al_schedule``), which spreads a dense start over the room the
    walls leave instead of into a ball."""
    c, dim = scene.container, scene.dim
    gids = np.asarray(gids, dtype=np.int64)
    r = 0.5 * np.asarray(diam, dtype=np.float64)
    if c.kind == "box":
        lo, hi = np.asarray(c.lo), np.asarray(c.hi)
        u = np.stack([uniforms(scene.seed, gids, 16 + k) for k in range(dim)], axis=1)
        return (lo[None, :] + r[:, None]) + u * ((hi - lo)[None, :] - 2.0 * r[:, None])
    centre = np.asarray(c.centre, dtype=np.float64)
    if c.kind == "sphere":
        unit = uniform_ball(scene.seed, gids, dim, 1.0)
        return centre[None, :] + unit * (c.radius - r)[:, None]
    # cylinder (3D): a uniform disc and a uniform height
    disc = uniform_ball(scene.seed, gids, 2, 1.0) * (c.radius - r)[:, None]
    top = c.height if c.height is not None else 2.0 * max(c.radius, _bed_height(scene))
    z = r + uniforms(scene.seed, gids, 19) * (top - 2.0 * r)
    return np.stack([centre[0] + disc[:, 0], centre[1] + disc[:, 1], centre[2] + z], axis=1)


def _bed_height(scene):
    """The height of the scene's spheres packed at the law's fraction over the container's
    floor (``fire_al_schedule.scene_law``)."""
    from mpipack.methods.fire_al_schedule import PACKING_FRACTION
    ball = {1: 2.0, 2: math.pi, 3: 4.0 / 3.0 * math.pi}[scene.dim]
    volume = scene.n * ball * scene.particles.mean_radius_power(scene.dim)
    return volume / (PACKING_FRACTION[scene.dim] * scene.container.section(scene.dim))
