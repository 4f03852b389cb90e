"""What a scene's start costs before a run: its overlapping pairs and the memory per rank of
its pair rows (``mpipack check``; the run's own guard is ``engine.memory``).

The start and the memory
------------------------
Gaussian start: each pair's separation is N(0, 2 sigma^2 I), so P(|X_k - X_l| < r) is the
regularised lower incomplete gamma function P(b/2, r^2 / (4 sigma^2)). Ball start: (r/R)^b per
pair (an upper bound). Lattice: the lattice's own shells within r (jitter ignored). A start file
(init.kind = "file"): its pairs closer than r, counted (a k-d tree). Memory per
rank: ``engine.memory.BYTES_PER_PARTICLE`` per particle plus 12 bytes per pair-row entry (two per pair
within d_kl + skin, at the start's skin: ``start_skin``), and ``engine.memory.BYTES_PER_ENTRY_PEAK``
per entry while rows are built: the run refuses a start whose rows do not fit (exit 2); the
check says so first and suggests the spread (init.sigma) that fits.
"""

import math

import numpy as np

from mpipack.analysis.stability import _gammainc_lower

BYTES_PER_ENTRY = 12  # a pair-row entry at rest (partner int32, lambda float64)


def pairs_within(scene, r):
    """Expected number of pairs of the start closer than r (see the module docstring)."""
    from mpipack.engine import initial as init
    n, b = scene.n, scene.dim
    total = 0.5 * n * (n - 1)
    kind = scene.init.kind
    if kind == "gaussian":
        sigma = init.gaussian_sigma(scene)
        return total * _gammainc_lower(b, r * r / (4.0 * sigma * sigma))
    if kind == "ball":
        R = init.ball_radius(scene)
        return total * min(1.0, (r / R) ** b)
    if kind == "file":
        from scipy.spatial import cKDTree
        tree = cKDTree(init.start_file(scene).x)
        return 0.5 * (float(tree.count_neighbors(tree, r)) - n)  # ordered pairs and self-pairs out
    s = float(scene.init.spacing)
    if r / s > 30:  # many shells: the lattice's density
        per_site = init.unit_ball_measure(b) * r ** b / _lattice_cell_measure(b, s)
    else:
        pts = init.lattice_points(max(50, int(4 * (r / s + 2) ** b * 2)), b, 1.0)
        per_site = int(np.count_nonzero(np.sqrt((pts ** 2).sum(axis=1)) < r / s)) - 1
    return min(total, 0.5 * n * per_site)


def _lattice_cell_measure(b, s):
    return {1: s, 2: math.sqrt(3) / 2 * s * s, 3: s ** 3 / math.sqrt(2)}[b]


def start_skin(scene):
    """The skin of the start's first build, in largest diameters (``Solver.initialise``):
    init.DENSE_START_SKIN for a dense start (``initial.is_dense``) of a method whose iterates
    do not depend on the rows' reach (not nested), else neighbor.skin. The squared radius of
    the uniform ball of the cloud's radius of gyration R_g: Gaussian (b+2) sigma^2 (R_g^2 =
    b sigma^2); ball its radius squared; lattice a packing, never dense; file from its
    positions."""
    from mpipack.engine import initial as init
    n, b, kind = scene.n, scene.dim, scene.init.kind
    if scene.method.nested or kind == "lattice":
        return float(scene.neighbor.skin)
    if kind == "gaussian":
        radius2 = (b + 2) * init.gaussian_sigma(scene) ** 2
    elif kind == "ball":
        radius2 = init.ball_radius(scene) ** 2
    else:
        x = init.start_file(scene).x
        radius2 = (b + 2) / b * float(((x - x.mean(axis=0)) ** 2).sum(axis=1).mean())
    dense = init.is_dense(n, b, n * scene.particles.mean_radius_power(b), radius2)
    return init.DENSE_START_SKIN if dense else float(scene.neighbor.skin)


def start_and_memory(scene, ranks, budget_bytes=None):
    """Overlapping pairs of the start, pair-row entries and memory per rank, and the spread
    that would fit (Gaussian starts)."""
    from mpipack.engine import initial as init
    from mpipack.engine.memory import BYTES_PER_ENTRY_PEAK, BYTES_PER_PARTICLE, available_memory_bytes
    p = scene.particles
    d_mean = p.d_mean
    skin = start_skin(scene)
    cut = p.d_max + skin * p.d_max  # the start's rows: every pair within d_kl + skin
    overl = pairs_within(scene, d_mean)
    row_pairs = pairs_within(scene, cut)
    entries = 2.0 * row_pairs / ranks
    per_rank_particles = math.ceil(scene.n / ranks) * BYTES_PER_PARTICLE[scene.dim]
    steady = per_rank_particles + entries * BYTES_PER_ENTRY
    peak = per_rank_particles + entries * BYTES_PER_ENTRY_PEAK
    if budget_bytes is None:
        gib = scene.neighbor.max_pair_gib
        budget_bytes = gib * 2 ** 30 if gib is not None else available_memory_bytes() / ranks
    out = {"overlapping_pairs": overl, "row_pairs": row_pairs, "start_skin": skin, "entries_per_rank": entries,
           "particles_bytes": per_rank_particles, "steady_bytes": steady, "peak_bytes": peak,
           "budget_bytes": budget_bytes, "fits": peak <= budget_bytes and per_rank_particles <= budget_bytes,
           "sigma": init.gaussian_sigma(scene) if scene.init.kind == "gaussian" else None,
           "suggested_sigma": None}
    if not out["fits"] and scene.init.kind == "gaussian" and per_rank_particles < budget_bytes:
        # the spread whose build peak uses at most 80% of the budget (bisection in log sigma)
        target = 0.8 * budget_bytes - per_rank_particles
        lo, hi = out["sigma"], 1e9
        for _ in range(200):
            mid = math.sqrt(lo * hi)
            e = 2.0 * 0.5 * scene.n * (scene.n - 1) * _gammainc_lower(scene.dim, cut * cut / (4 * mid * mid)) / ranks
            if e * BYTES_PER_ENTRY_PEAK > target:
                lo = mid
            else:
                hi = mid
        out["suggested_sigma"] = hi
    return out
