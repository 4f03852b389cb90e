"""The measures of a packing, on one rank's spheres by space (``halo.Local``): the math of each
measure, with its global sums reduced exactly so that every number is the same on any rank
count. Each function returns plain numbers (a "summary"), the table behind its figure, and
what its picture needs. b is the dimension, d_ij = (d_i + d_j) / 2, Xbar the centre of mass.

    density     phi(R) = |union_i B_i ∩ B(Xbar, R)| / |B(Xbar, R)|, from each sphere's exact
                intersection with the ball (paper, Figs. 8b and 10a); its plateau
    neighbours  n_i = #{j : |X_i - X_j| < t d_ij}, t = 1.1 (Fig. 10b)
    contacts    the network of pairs with lambda_ij > 0 (the snapshot's multipliers) and of pairs
                with gap |X_i - X_j| / d_ij - 1 < tol; Z, rattlers (< b + 1 contacts, removed
                until none is left), Z - 2b of the rest
    pressure    mu_i = sum_j lambda_ij (the snapshot's field)
    gr          g(r) of the interior: centres within the density plateau's ball, shrunk by r_max
                (at most GR_CENTRES of them, every k-th by gid)
    order       2D: psi6_i = (1/n_i) sum_j exp(6 i theta_ij); 3D: Steinhardt q6, Q6_i and the
                neighbour-averaged Qbar6_i (Lechner and Dellago 2008), crystalline share (ten
                Wolde, Ruiz-Montero and Frenkel 1996: >= 7 bonds with d6 > 0.7)
"""

import math

import numpy as np

from mpipack.kernels import metrics
from mpipack.parallel import exactsum

from . import halo

# the densest packings: hexagonal discs and FCC/HCP spheres; 1D: a chain
MAX_DENSITY = {1: 1.0, 2: math.pi / (2.0 * math.sqrt(3.0)), 3: math.pi / (3.0 * math.sqrt(2.0))}
PLATEAU_TOLERANCE = 0.02      # phi(R) within 2 % of the plateau value
SOLID_BOND = 0.7              # d6 above which a bond is solid-like
SOLID_BONDS = 7               # solid bonds above which a sphere is crystalline (of 12 in FCC)
GR_CENTRES = 50_000           # g(r): at most this many centres (every k-th interior sphere by gid)
GR_CHUNK = 5_000              # g(r): centres per tree query (bounds the memory of the pair list)


def ball_measure(dim, R):
    return metrics.ball_measure(dim, R)


# ---- the centre and the size of the cluster --------------------------------------------------

def centre_of_mass(comm, local, n):
    """Xbar = (1/N) sum_i X_i, exact (the same on any rank count); shape (b,)."""
    own = local.x[:local.n_own]
    return np.array(halo.exact_totals(comm, [own[:, k] for k in range(own.shape[1])])) / n


def gyration_radius(comm, local, xbar, n):
    """R_g = sqrt((1/N) sum_i |X_i - Xbar|^2), exact."""
    own = local.x[:local.n_own]
    return math.sqrt(halo.exact_total(comm, ((own - xbar) ** 2).sum(axis=1)) / n)


def cluster_radius(dim, r_gyr):
    """The radius of the uniform ball with this radius of gyration: R_g^2 = b/(b+2) R^2."""
    return r_gyr * math.sqrt((dim + 2.0) / dim)


# ---- density -----------------------------------------------------------------------------------

def density_profile(comm, local, xbar, radii):
    """phi(R) for each R of radii (shape (K,)): exact sums of |B_i ∩ B(Xbar, R)| over the
    owned spheres, reduced exactly; shape (K,). NaN where R = 0 (no ball to fill: the
    gyration radius of a single sphere)."""
    radii = np.ascontiguousarray(radii, dtype=np.float64)
    acc = exactsum.new_accumulator(len(radii))
    n = local.n_own
    metrics.covered_measure(np.ascontiguousarray(local.x[:n]), np.ascontiguousarray(local.diam[:n]), n,
                            np.ascontiguousarray(xbar, dtype=np.float64), radii, acc)
    acc = comm.allreduce(acc)
    dim = local.x.shape[1]
    balls = [metrics.ball_measure(dim, R) for R in radii]
    return np.array([exactsum.value(acc, q) / m if m > 0 else math.nan for q, m in enumerate(balls)])


def plateau(radii, phi, d_mean, r_cluster, tol=PLATEAU_TOLERANCE):
    """(value, R_from, R_to) of the plateau of phi(R): its median over [2 d, 0.7 R_c] (the
    centre is noisy at small R, the surface thins it out), and the widest run of radii around
    that range's middle where phi stays within ``tol`` of it. (nan, nan, nan) if the cluster is
    too small to have one (fewer than 3 radii in the range)."""
    inner = (radii >= 2.0 * d_mean) & (radii <= 0.7 * r_cluster)
    if inner.sum() < 3:
        return math.nan, math.nan, math.nan
    value = float(np.median(phi[inner]))
    ok = np.abs(phi - value) <= tol * value
    mid = int(np.flatnonzero(inner)[inner.sum() // 2])
    if not ok[mid]:
        return value, math.nan, math.nan
    a = mid
    while a > 0 and ok[a - 1]:
        a -= 1
    b = mid
    while b + 1 < len(ok) and ok[b + 1]:
        b += 1
    return value, float(radii[a]), float(radii[b])


# ---- pairs of neighbours -----------------------------------------------------------------------

def close_pairs(local, factor, d_max):
    """Directed pairs (i, j), i an owned row and j any other row, with |X_i - X_j| < factor d_ij,
    sorted by (gid_i, gid_j): arrays i, j (row indices) and r (distances)."""
    from scipy.spatial import cKDTree
    n = local.n_own
    empty = (np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0))
    if n == 0:
        return empty
    reach = factor * d_max * (1.0 + 1e-9)
    found = cKDTree(local.x[:n]).sparse_distance_matrix(cKDTree(local.x), reach, output_type="ndarray")
    i, j = found["i"].astype(np.int64), found["j"].astype(np.int64)
    keep = local.gid[i] != local.gid[j]
    i, j = i[keep], j[keep]
    r = np.sqrt(((local.x[j] - local.x[i]) ** 2).sum(axis=1))
    keep = r < factor * 0.5 * (local.diam[i] + local.diam[j])
    i, j, r = i[keep], j[keep], r[keep]
    order = np.lexsort((local.gid[j], local.gid[i]))
    return i[order], j[order], r[order]


def per_sphere_sum(i, values, n):
    """sum over the pairs of each owned sphere, in the pairs' (gid) order: shape (n, ...)."""
    if values.ndim == 1:
        return np.bincount(i, weights=values, minlength=n)[:n]
    return np.stack([np.bincount(i, weights=values[:, k], minlength=n)[:n] for k in range(values.shape[1])], axis=1)


def count_histogram(comm, counts):
    """Global histogram of integer counts: (k = 0 .. max, how many spheres have k)."""
    top = int(comm.allreduce(np.array([counts.max() if len(counts) else 0], np.int64), "max")[0])
    return halo.total(comm, np.bincount(counts, minlength=top + 1))


# ---- contacts ----------------------------------------------------------------------------------

def rattlers(comm, local, i, j, dim):
    """Alive mask of the owned spheres after removing rattlers (fewer than b + 1 contacts among
    the spheres still alive) until none is left, and the rounds it took (collective)."""
    n = local.n_own
    alive = np.ones(n, dtype=bool)
    rounds = 0
    while True:
        alive_all = local.with_halo(alive.astype(np.int8)).astype(bool)
        count = np.bincount(i[alive_all[j]], minlength=n)[:n]
        gone = alive & (count < dim + 1)
        if int(halo.total(comm, np.array([gone.sum()]))[0]) == 0:
            return alive, rounds
        alive &= ~gone
        rounds += 1


def contact_summary(comm, local, i, j, dim, n_total):
    """Z, rattlers and isostaticity of a contact network given as directed pairs (i owned)."""
    n = local.n_own
    count = np.bincount(i, minlength=n)[:n]
    hist = count_histogram(comm, count)
    z = float(np.dot(np.arange(len(hist)), hist)) / n_total
    alive, rounds = rattlers(comm, local, i, j, dim)
    alive_all = local.with_halo(alive.astype(np.int8)).astype(bool)
    keep = alive[i] & alive_all[j]
    count_alive = np.bincount(i[keep], minlength=n)[:n]
    n_alive, bonds = (int(v) for v in halo.total(comm, np.array([alive.sum(), count_alive.sum()])))
    z_alive = bonds / n_alive if n_alive else math.nan
    return {"Z": z, "rattlers": n_total - n_alive, "rattler_share": (n_total - n_alive) / n_total,
            "Z_without_rattlers": z_alive, "isostaticity": z_alive - 2 * dim,
            "rattler_rounds": rounds, "histogram": hist}, alive


# ---- g(r) --------------------------------------------------------------------------------------

def pair_distribution(comm, local, xbar, r_bulk, edges, max_centres=GR_CENTRES):
    """g(r) of the interior: centres are the spheres with |X_i - Xbar| <= r_bulk - r_max (their
    shells lie inside the ball of radius r_bulk; at most ``max_centres`` of them, every k-th by
    gid, so the choice does not depend on the ranks), partners any sphere; normalised by the
    number density rho of the ball of radius r_bulk: g(r_k) = counts_k / (N_c rho |shell_k|).
    Returns (g, counts (K,), N_c, rho)."""
    from scipy.spatial import cKDTree
    dim = local.x.shape[1]
    r_max = float(edges[-1])
    n = local.n_own
    dist = np.sqrt(((local.x[:n] - xbar) ** 2).sum(axis=1))
    inside = dist <= r_bulk - r_max
    n_inside, n_bulk = (int(v) for v in halo.total(comm, np.array([inside.sum(), (dist <= r_bulk).sum()])))
    stride = max(1, -(-n_inside // max_centres))
    centre = inside & (local.gid[:n] % stride == 0)
    n_centres = int(halo.total(comm, np.array([centre.sum()]))[0])
    counts = np.zeros(len(edges) - 1, np.int64)
    rows = np.flatnonzero(centre)
    if len(rows):
        tree = cKDTree(local.x)
        for start in range(0, len(rows), GR_CHUNK):
            c = rows[start:start + GR_CHUNK]
            found = cKDTree(local.x[c]).sparse_distance_matrix(tree, r_max * (1.0 + 1e-9), output_type="ndarray")
            ci, pj = c[found["i"]], found["j"]
            keep = local.gid[ci] != local.gid[pj]
            ci, pj = ci[keep], pj[keep]
            r = np.sqrt(((local.x[pj] - local.x[ci]) ** 2).sum(axis=1))  # the same bits on any rank
            k = np.searchsorted(edges, r, side="right") - 1                # edges[k] <= r < edges[k+1]
            counts += np.bincount(k[(k >= 0) & (k < len(counts))], minlength=len(counts))[:len(counts)]
    counts = halo.total(comm, counts)
    rho = n_bulk / metrics.ball_measure(dim, r_bulk) if r_bulk > 0 else math.nan
    volume = np.diff([metrics.ball_measure(dim, r) if r > 0 else 0.0 for r in edges])
    with np.errstate(divide="ignore", invalid="ignore"):
        g = counts / (n_centres * rho * volume) if n_centres else np.full(len(counts), math.nan)
    return g, counts, n_centres, rho


# ---- order -------------------------------------------------------------------------------------

def hexatic(local, i, j):
    """psi6_i = (1/n_i) sum_j exp(6 i theta_ij) of the owned discs (complex, (n_own,)); 0 for
    a disc without neighbours."""
    n = local.n_own
    d = local.x[j] - local.x[i]
    theta = np.arctan2(d[:, 1], d[:, 0])
    re = per_sphere_sum(i, np.cos(6.0 * theta), n)
    im = per_sphere_sum(i, np.sin(6.0 * theta), n)
    k = np.maximum(np.bincount(i, minlength=n)[:n], 1)
    return (re + 1j * im) / k


def steinhardt(local, i, j, ell=6):
    """q_lm(i) = (1/n_i) sum_j Y_lm(r_ij) of the owned spheres, shape (n_own, 2l + 1) complex,
    and Q_l(i) = sqrt(4 pi / (2l + 1) sum_m |q_lm(i)|^2)."""
    from scipy.special import sph_harm_y
    n = local.n_own
    d = local.x[j] - local.x[i]
    r = np.sqrt((d ** 2).sum(axis=1))
    polar = np.arccos(np.clip(d[:, 2] / np.where(r > 0, r, 1.0), -1.0, 1.0))
    azimuth = np.arctan2(d[:, 1], d[:, 0])
    k = np.maximum(np.bincount(i, minlength=n)[:n], 1)
    q = np.empty((n, 2 * ell + 1), dtype=complex)
    for col, m in enumerate(range(-ell, ell + 1)):
        y = sph_harm_y(ell, m, polar, azimuth)
        q[:, col] = (per_sphere_sum(i, y.real, n) + 1j * per_sphere_sum(i, y.imag, n)) / k
    return q, np.sqrt(4.0 * np.pi / (2 * ell + 1) * (np.abs(q) ** 2).sum(axis=1))


def averaged_q(local, i, j, q, ell=6):
    """Qbar_l(i) from q_lm averaged over the sphere and its neighbours (q of every row: owned
    then halo, shape (n_rows, 2l + 1))."""
    n = local.n_own
    k = np.bincount(i, minlength=n)[:n]
    sq = np.stack([per_sphere_sum(i, q[j, c].real, n) + 1j * per_sphere_sum(i, q[j, c].imag, n)
                   for c in range(q.shape[1])], axis=1)
    qbar = (q[:n] + sq) / (k + 1)[:, None]
    return np.sqrt(4.0 * np.pi / (2 * ell + 1) * (np.abs(qbar) ** 2).sum(axis=1))


def solid_bonds(local, i, j, q):
    """Number of solid-like bonds of each owned sphere: d6 = Re(q6(i) . q6(j)*) / (|q6(i)||q6(j)|)
    above SOLID_BOND (q of every row, owned then halo)."""
    n = local.n_own
    norm = np.sqrt((np.abs(q) ** 2).sum(axis=1))
    dot = (q[i] * np.conj(q[j])).sum(axis=1).real
    with np.errstate(divide="ignore", invalid="ignore"):
        d6 = np.where((norm[i] > 0) & (norm[j] > 0), dot / (norm[i] * norm[j]), 0.0)
    return np.bincount(i[d6 > SOLID_BOND], minlength=n)[:n]
