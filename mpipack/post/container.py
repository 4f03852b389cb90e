"""A packing inside its container (``container.kind`` box, cylinder, sphere): the packing
fraction, its profile along the axis and from the wall, the wall contacts. On one rank's own
spheres (``halo.Local``), every per-sphere number from that sphere alone and every sum exact
(``halo.exact_totals``): the same on any rank count.

The container comes from the run's scene table (``pk.scene["container"]``); its walls are the
rows of ``kernels.walls.walls_of`` (s_iw = the signed distance of centre i inside wall w).

Packing fraction  phi_C = sum_i |B_i ∩ C| / |C|, with |B_i ∩ C| = |B_i| - sum_w cut_iw, cut_iw
                  the part of B_i beyond wall w (r_i the radius, h = r_i - s_iw > 0):
                    plane     a cap: 3D pi h^2 (3 r - h) / 3; 2D r^2 acos((r - h)/r) - (r - h)
                              sqrt(2 r h - h^2); 1D h (closed forms)
                    cylinder  side: the integral over z of the area of the slice's disc (radius
                              sqrt(r^2 - z^2), at rho from the axis) outside the circle R:
                              Gauss-Legendre, QUADRATURE nodes after z = z0 (1 - t^2), which
                              makes the integrand smooth at the slice where the cut begins
                              (tested against scipy's adaptive quadrature to 1e-12 of |B_i|)
                    sphere    |B_i ∩ C| = the lens of two balls (``kernels.metrics``, exact)
                  The cuts of two walls never overlap when the sphere's centre lies inside both
                  (s >= 0) with s_1^2 + s_2^2 >= r^2 (walls at right angles: box, a cylinder's
                  side and floor), or when the walls are opposite; any other sphere (one poking
                  out by more than 0.29 r, not a packing) is counted and warned about.
Axis profile      (box, cylinder; 2D and 3D) slabs of height d_mean along the last axis (y in
                  2D, z in 3D) from the floor (box lo, cylinder centre) to the top (box hi, the
                  lid, or for an open cylinder the highest sphere's top): sum_i |B_i ∩ slab|
                  (exact: pi (r^2 u - u^3/3) in 3D, u sqrt(r^2 - u^2) + r^2 asin(u/r) in 2D,
                  clipped to the floor and lid) less the side walls' cuts, shared by the slabs
                  in proportion to the sphere's part in each, over |C ∩ slab|.
Wall profile      phi(t), t a point's distance inside a wall, bins of d_mean/10 over t < 5 d_mean,
                  each wall's own and pooled over the walls: phi = sum_w sum_i |B_i ∩ {t_1 <=
                  s_w < t_2}| / sum_w |C ∩ {t_1 <= s_w < t_2}|, the balls' parts exact (a
                  slab's primitive for a plane, ``cylinder_cut`` for a cylinder's side, the
                  lens for a sphere), the shells' measures closed forms (``wall_inner_measure``).
                  A point near two walls counts for each. Also the centres' histogram of
                  s_iw (pooled): the layering of the wall.
Nearest wall      phi(t_1, t_2) over the points whose nearest wall lies in [t_1, t_2): C_t the
                  container shrunk by t (clipped at a fixed height below a free surface), the
                  points at least t from every wall (convex containers), phi = sum_i (|B_i ∩
                  C_t1| - |B_i ∩ C_t2|) / (|C_t1| - |C_t2|), |B_i ∩ C_t| whole (``ball_in_shrunk``:
                  closed forms in 1D and 2D and for a sphere, the slices' closed-form areas by
                  Gauss-Legendre in 3D), each ball's differences summed exactly.
"""

import math
import types

import numpy as np

from mpipack.kernels import metrics, walls as wall_rows
from mpipack.parallel import exactsum

from . import halo

QUADRATURE = 64          # Gauss-Legendre nodes of a cylinder side's cut
WALL_BINS_PER_D = 10     # the wall profile's bins per mean diameter
WALL_RANGE_D = 5         # ... over this many mean diameters from the wall


def of_scene(scene, dim):
    """The scene's container (a namespace with the Container's fields), or None."""
    table = scene.get("container") if isinstance(scene, dict) else None
    if not isinstance(table, dict) or table.get("kind", "none") in ("none", None):
        return None
    c = types.SimpleNamespace(**{k: table.get(k) for k in ("kind", "lo", "hi", "centre", "radius", "height")})
    c.walls = wall_rows.walls_of(c, dim)
    c.names = wall_rows.wall_names(c, dim)
    return c


def binned_sum(comm, cols, vals, nbins):
    """sum over all ranks of vals by bin: (nbins,) float64, each bin's sum exact (``exactsum``:
    the same bits on any number of ranks, whatever the order of the terms). cols (m,) the
    terms' bins in [0, nbins), vals (m,) the terms (lists or arrays). Collective."""
    cols, vals = np.asarray(cols, np.int64), np.asarray(vals, np.float64)
    order = np.argsort(cols, kind="stable")
    cols, vals = cols[order], vals[order]
    cuts = np.searchsorted(cols, np.arange(nbins + 1))
    acc = exactsum.new_accumulator(nbins)
    for q in range(nbins):
        exactsum.accumulate(np.ascontiguousarray(vals[cuts[q]:cuts[q + 1]]), acc, q)
    acc = comm.allreduce(acc)
    return np.array([exactsum.value(acc, q) for q in range(nbins)])


def gaps(walls, x):
    """s (m, n_walls): each centre's signed distance inside each wall (element by element, the
    same bits for a sphere on any rank)."""
    m, dim = x.shape
    full = np.zeros((m, 3))
    full[:, :dim] = x
    out = np.empty((m, walls.shape[0]))
    for w, row in enumerate(walls):
        if row[0] == wall_rows.PLANE:
            out[:, w] = full[:, 0] * row[1] + full[:, 1] * row[2] + full[:, 2] * row[3] - row[4]
        else:
            v = full - row[1:4][None, :]
            if row[0] == wall_rows.CYLINDER:
                v[:, int(row[5])] = 0.0
            out[:, w] = row[4] - np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])
    return out


def cap(dim, r, h):
    """The part of a ball of radius r beyond a plane at r - h from its centre (0 <= h <= 2r)."""
    h = min(max(h, 0.0), 2.0 * r)
    if dim == 3:
        return math.pi * h * h * (3.0 * r - h) / 3.0
    if dim == 2:
        a = r - h
        return r * r * math.acos(max(-1.0, min(1.0, a / r))) - a * math.sqrt(max(2.0 * r * h - h * h, 0.0))
    return h


def _segment(rho, theta):
    """The area of a disc of radius rho beyond a chord seen under the half angle theta from its
    centre: rho^2 (theta - sin theta cos theta); a series for small theta (no cancellation)."""
    if theta < 0.1:
        x = 2.0 * theta
        x2 = x * x
        return rho * rho * x * x2 * (1.0 / 12.0 - x2 * (1.0 / 240.0 - x2 * (1.0 / 10080.0 - x2 * (
            1.0 / 725760.0 - x2 / 79833600.0))))
    return rho * rho * (theta - math.sin(theta) * math.cos(theta))


def _outside_area(a, big, d):
    """The area of the disc of radius a whose centre is d from the origin outside the circle
    of radius big about the origin: the disc's segment beyond the circles' common chord less
    the circle's segment beyond it, each small where the other is (no cancellation)."""
    if d >= a + big:
        return math.pi * a * a
    if d + a <= big:
        return 0.0
    if d + big <= a:
        return math.pi * (a * a - big * big)
    u = (a - (d - big)) * (a + (d - big)) / (2.0 * d)   # big - x_c, x_c the chord's abscissa
    y = math.sqrt(max(u * (2.0 * big - u), 0.0))        # the chord's half length
    x_c = big - u
    e = ((big - d) * (big + d) - a * a) / (2.0 * d)     # x_c - d
    return max(_segment(a, math.atan2(y, e)) - _segment(big, math.atan2(y, x_c)), 0.0)


_NODES = None


def _nodes():
    global _NODES
    if _NODES is None:
        t, w = np.polynomial.legendre.leggauss(QUADRATURE)
        _NODES = (0.5 * (t + 1.0), 0.5 * w)  # on [0, 1]
    return _NODES


def cylinder_cut(r, rho, big):
    """The part of a ball of radius r, centre rho from the axis, outside the cylinder of
    radius big (3D): 2 int_0^r A(z) dz, A(z) the area of the slice's disc
    (a = sqrt(r^2 - z^2)) outside the circle. A vanishes for a <= s = big - rho (s > 0) and
    is the whole disc for a <= -s (s < 0, closed form there); each smooth piece by Gauss-Legendre
    after z = z0 (1 - t^2) (z0 where the piece ends: A ~ (z0 - z)^(3/2) there)."""
    if big <= 0.0:
        return 4.0 / 3.0 * math.pi * r ** 3
    s = big - rho
    if s >= r:
        return 0.0
    z0 = math.sqrt(r * r - s * s) if abs(s) < r else 0.0
    whole = 0.0
    if s < 0:  # z in [z0, r]: the slice lies wholly outside
        whole = math.pi * ((r * r * r - r ** 3 / 3.0) - (r * r * z0 - z0 ** 3 / 3.0))
    t, w = _nodes()
    total = 0.0
    for tk, wk in zip(t.tolist(), w.tolist()):
        z = z0 * (1.0 - tk * tk)
        a = math.sqrt(max(r * r - z * z, 0.0))
        total += wk * 2.0 * z0 * tk * _outside_area(a, big, rho)
    return 2.0 * (total + whole)


def inside_volumes(c, dim, x, diam):
    """(|B_i ∩ C| (m,), the side walls' cut of each sphere (m,), spheres whose cuts may overlap
    (count)) of the centres x (m, b) and diameters (m,)."""
    r = 0.5 * diam
    full = np.array([metrics.ball_measure(dim, float(v)) for v in r]) if len(r) else np.zeros(0)
    vol = full.copy()
    side = np.zeros(len(r))
    doubtful = 0
    if len(r) == 0:
        return vol, side, doubtful
    s = gaps(c.walls, x)
    if c.kind == "sphere":
        R = float(c.radius)
        for i in np.flatnonzero(s[:, 0] < r):
            vol[i] = metrics.intersection(dim, R - s[i, 0], r[i], R)
        return vol, side, doubtful
    axis_of = lambda w: int(np.argmax(np.abs(c.walls[w, 1:4]))) if c.walls[w, 0] == wall_rows.PLANE else -1
    for i in np.flatnonzero((s < r[:, None]).any(axis=1)):
        cutting = [w for w in range(c.walls.shape[0]) if s[i, w] < r[i]]
        for a in range(len(cutting)):
            for b in range(a + 1, len(cutting)):
                wa, wb = cutting[a], cutting[b]
                opposite = axis_of(wa) >= 0 and axis_of(wa) == axis_of(wb)
                if not opposite and not (s[i, wa] >= 0 and s[i, wb] >= 0
                                         and s[i, wa] ** 2 + s[i, wb] ** 2 >= r[i] ** 2):
                    doubtful += 1
        for w in cutting:
            if c.walls[w, 0] == wall_rows.PLANE:
                cut = cap(dim, r[i], r[i] - s[i, w])
            else:
                cut = cylinder_cut(r[i], float(c.walls[w, 4]) - s[i, w], float(c.walls[w, 4]))
            vol[i] -= cut
            if c.walls[w, 0] != wall_rows.PLANE or axis_of(w) != dim - 1:
                side[i] += cut
    return np.maximum(vol, 0.0), side, doubtful


def measure(c, dim, top=None):
    """|C| (length^b); an open cylinder up to ``top``."""
    if c.kind == "box":
        return math.prod(float(h) - float(l) for l, h in zip(c.lo, c.hi))
    if c.kind == "cylinder":
        return math.pi * float(c.radius) ** 2 * (float(c.height) if c.height is not None else top - float(c.centre[2]))
    return metrics.ball_measure(dim, float(c.radius))


def cross_section(c, dim):
    """The measure of the container's cut across its last axis (box, cylinder)."""
    if c.kind == "cylinder":
        return math.pi * float(c.radius) ** 2
    return math.prod(float(c.hi[k]) - float(c.lo[k]) for k in range(dim - 1))


def axis_range(c, dim, top_of_spheres):
    """(floor, top) of the container along the last axis (box, cylinder), else None."""
    if c.kind == "box" and dim >= 2:
        return float(c.lo[dim - 1]), float(c.hi[dim - 1])
    if c.kind == "cylinder":
        z0 = float(c.centre[2])
        return z0, (z0 + float(c.height)) if c.height is not None else top_of_spheres
    return None


def _slab_primitive(dim, r, u):
    """int_{-r}^{u} of the ball's slice measure (u clipped to [-r, r])."""
    u = min(max(u, -r), r)
    if dim == 1:
        return u + r
    if dim == 3:
        return math.pi * (r * r * u - u ** 3 / 3.0) + 2.0 * math.pi * r ** 3 / 3.0
    return u * math.sqrt(max(r * r - u * u, 0.0)) + r * r * math.asin(u / r) + 0.5 * math.pi * r * r


def axis_profile(comm, c, dim, x, diam, vol, side, edges):
    """Exact sums over the slabs [edges_q, edges_q+1) of |B_i ∩ C ∩ slab| (the side cut shared
    in proportion): (K,) floats, the same on any rank count."""
    k = dim - 1
    lo_c, hi_c = float(edges[0]), float(edges[-1])
    rows, vals = [], []
    for i in range(len(diam)):
        r = 0.5 * float(diam[i])
        z = float(x[i, k])
        q0 = max(int(np.searchsorted(edges, z - r, side="right")) - 1, 0)
        q1 = min(int(np.searchsorted(edges, z + r, side="left")), len(edges) - 1)
        parts = []
        for q in range(q0, q1):
            a, b = max(float(edges[q]), lo_c), min(float(edges[q + 1]), hi_c)
            parts.append((q, max(_slab_primitive(dim, r, b - z) - _slab_primitive(dim, r, a - z), 0.0)))
        whole = sum(p for _, p in parts)
        keep = (whole - side[i]) / whole if whole > 0 else 0.0
        for q, p in parts:
            rows.append(q)
            vals.append(p * keep)
    return binned_sum(comm, rows, vals, len(edges) - 1)


def part_inside(c, w, dim, r, s_iw, t):
    """G_w(t) = |B_i ∩ {p : s_w(p) >= t}|: the part of a ball (radius r, centre s_iw inside wall
    w) at least t inside that wall (exact: a slab's primitive, a sphere's lens; a cylinder
    side's by ``cylinder_cut``)."""
    row = c.walls[w]
    if row[0] == wall_rows.PLANE:
        return metrics.ball_measure(dim, r) - _slab_primitive(dim, r, t - s_iw)
    big = float(row[4])
    if row[0] == wall_rows.CYLINDER:
        return metrics.ball_measure(dim, r) - cylinder_cut(r, big - s_iw, big - t)
    inner = big - t
    return metrics.intersection(dim, big - s_iw, r, inner) if inner > 0 else 0.0


def wall_inner_measure(c, dim, w, t, top=None):
    """H_w(t) = |C ∩ {p : s_w(p) >= t}|: the container's points at least t inside wall w."""
    row = c.walls[w]
    if c.kind == "box":
        k = int(np.argmax(np.abs(row[1:4])))
        return max(float(c.hi[k]) - float(c.lo[k]) - t, 0.0) * math.prod(
            float(c.hi[j]) - float(c.lo[j]) for j in range(dim) if j != k)
    if c.kind == "cylinder":
        height = float(c.height) if c.height is not None else top - float(c.centre[2])
        if row[0] == wall_rows.CYLINDER:
            return math.pi * max(float(c.radius) - t, 0.0) ** 2 * height
        return math.pi * float(c.radius) ** 2 * max(height - t, 0.0)
    return metrics.ball_measure(dim, max(float(c.radius) - t, 0.0))


def wall_profile(comm, c, dim, x, diam, edges, top=None):
    """The profile from the walls, pooled over the walls: (covered (K,), shell (K,), centres
    (K,) int) with covered_q = sum_w sum_i |B_i ∩ {edges_q <= s_w < edges_q+1}| (exact sums),
    shell_q = sum_w |C ∩ {edges_q <= s_w < edges_q+1}| and centres_q = #{(i, w) : edges_q <=
    s_iw < edges_q+1}. A point near two walls counts for each; a ball's part beyond another
    wall (its cut, at most ``inside_volumes``' side cut) is not taken out."""
    nbins = len(edges) - 1
    width = float(edges[1] - edges[0])
    r = 0.5 * diam
    s = gaps(c.walls, x) if len(diam) else np.zeros((0, c.walls.shape[0]))
    centres = np.zeros(nbins, np.int64)
    cols, vals = [], []
    for w in range(c.walls.shape[0]):
        kc = np.floor(s[:, w] / width).astype(np.int64)
        ok = (s[:, w] >= 0) & (kc < nbins)
        centres += np.bincount(kc[ok], minlength=nbins)[:nbins]
        for i in np.flatnonzero(s[:, w] - r < edges[-1]):
            ri, si = float(r[i]), float(s[i, w])
            q0 = max(int(np.searchsorted(edges, si - ri, side="right")) - 1, 0)
            q1 = min(int(np.searchsorted(edges, si + ri, side="left")), nbins)
            g = [part_inside(c, w, dim, ri, si, float(edges[q])) for q in range(q0, q1 + 1)]
            for q in range(q0, q1):
                cols.append(q)
                vals.append(max(g[q - q0] - g[q - q0 + 1], 0.0))
    covered = binned_sum(comm, cols, vals, nbins)
    shell = np.array([sum(wall_inner_measure(c, dim, w, float(edges[q]), top)
                          - wall_inner_measure(c, dim, w, float(edges[q + 1]), top) for w in range(c.walls.shape[0]))
                      for q in range(nbins)])
    return covered, shell, halo.total(comm, centres)


# ---- the profile from the nearest wall -------------------------------------------------------------
#
# C_t = the container shrunk by t (a box: lo + t, hi - t; a cylinder: radius - t, floor + t, lid - t;
# a sphere: radius - t), clipped at a height ``clip`` fixed independent of t (the bed's top: a free
# surface is no wall). In a convex container the points whose nearest wall is at least t away are
# exactly C_t, so the points whose nearest wall lies in [t_1, t_2) are C_t1 \ C_t2 and
#   phi(t_1, t_2) = sum_i (|B_i ∩ C_t1| - |B_i ∩ C_t2|) / (|C_t1| - |C_t2|).

def _smooth_pieces(f, lo, hi, breaks):
    """int_lo^hi f(z) dz, f (vectorised) smooth between the points ``breaks`` (where it may
    behave like (z - z_b)^(1/2) or ^(3/2)): Gauss-Legendre on each piece [p, q] after
    z = p + (q - p) (3 u^2 - 2 u^3), which flattens both ends (dz = 6 (q - p) u (1 - u) du)."""
    if hi <= lo:
        return 0.0
    cuts = sorted({lo, hi, *(b for b in breaks if lo < b < hi)})
    u, w = _nodes()
    jac = w * 6.0 * u * (1.0 - u)
    shape = u * u * (3.0 - 2.0 * u)
    total = 0.0
    for p, q in zip(cuts[:-1], cuts[1:]):
        total += float(np.dot(jac, f(p + (q - p) * shape))) * (q - p)
    return total


def _half_disc_primitive(a, x):
    """W(x) = int_{-a}^{x} sqrt(a^2 - u^2) du for x in [-a, a] (arrays; 0 where a = 0)."""
    safe = np.where(a > 0, a, 1.0)
    return np.where(a > 0, 0.5 * (x * np.sqrt(np.maximum(a * a - x * x, 0.0))
                                  + a * a * np.arcsin(np.clip(x / safe, -1.0, 1.0))) + 0.25 * math.pi * a * a, 0.0)


def _below(a, x1, x2, y):
    """The area of the disc of radius a (array) about the origin with x1 <= x <= x2 and y' < y:
    int_x1^x2 (clamp(y, -w, w) + w) dx, w = sqrt(a^2 - x^2); with b = sqrt(a^2 - y^2) the
    integrand is w + sign(y) w for |x| >= b and y + w for |x| < b (closed form)."""
    sgn = 1.0 if y >= 0 else -1.0
    b = np.sqrt(np.maximum(a * a - y * y, 0.0))

    def prim(x):
        x = np.clip(x, -a, a)
        return (_half_disc_primitive(a, x) + sgn * _half_disc_primitive(a, np.minimum(x, -b))
                + y * (np.clip(x, -b, b) + b)
                + sgn * (_half_disc_primitive(a, np.maximum(x, b)) - _half_disc_primitive(a, b)))
    return prim(np.asarray(x2, dtype=float)) - prim(np.asarray(x1, dtype=float))


def disc_in_rectangle(a, x1, x2, y1, y2):
    """|disc(0, a) ∩ [x1, x2] x [y1, y2]| for an array of radii a (closed form)."""
    a = np.asarray(a, dtype=float)
    if x2 <= x1 or y2 <= y1:
        return np.zeros_like(a)
    return np.maximum(_below(a, x1, x2, y2) - _below(a, x1, x2, y1), 0.0)


def _segment_v(rho, theta):
    """``_segment`` on arrays."""
    x = 2.0 * theta
    x2 = x * x
    series = rho * rho * x * x2 * (1.0 / 12.0 - x2 * (1.0 / 240.0 - x2 * (1.0 / 10080.0 - x2 * (
        1.0 / 725760.0 - x2 / 79833600.0))))
    return np.where(theta < 0.1, series, rho * rho * (theta - np.sin(theta) * np.cos(theta)))


def disc_outside_circle(a, big, d):
    """``_outside_area`` on an array of radii a (the disc's centre d from the circle's)."""
    a = np.asarray(a, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        dd = max(d, 1e-300)
        u = (a - (d - big)) * (a + (d - big)) / (2.0 * dd)
        y = np.sqrt(np.maximum(u * (2.0 * big - u), 0.0))
        e = ((big - d) * (big + d) - a * a) / (2.0 * dd)
        mid = np.maximum(_segment_v(a, np.arctan2(y, e)) - _segment_v(big, np.arctan2(y, big - u)), 0.0)
    return np.where(d >= a + big, math.pi * a * a,
                    np.where(d + a <= big, 0.0, np.where(d + big <= a, math.pi * (a * a - big * big), mid)))


def shrunk(c, dim, t, clip=None):
    """C_t as bounds: a box's (lo (dim,), hi (dim,)); a cylinder's (radius, floor, top); a
    sphere's radius. ``clip`` caps the last coordinate (box, cylinder)."""
    if c.kind == "box":
        lo = np.array([float(v) + t for v in c.lo[:dim]])
        hi = np.array([float(v) - t for v in c.hi[:dim]])
        if clip is not None:
            hi[-1] = min(hi[-1], clip)
        return lo, hi
    if c.kind == "cylinder":
        z0 = float(c.centre[2])
        top = z0 + float(c.height) - t if c.height is not None else math.inf
        if clip is not None:
            top = min(top, clip)
        return float(c.radius) - t, z0 + t, top
    return float(c.radius) - t


def shrunk_measure(c, dim, t, clip=None):
    """|C_t| (clipped)."""
    b = shrunk(c, dim, t, clip)
    if c.kind == "box":
        return math.prod(max(h - l, 0.0) for l, h in zip(b[0], b[1]))
    if c.kind == "cylinder":
        radius, floor, top = b
        return math.pi * max(radius, 0.0) ** 2 * max(top - floor, 0.0) if math.isfinite(top) else math.inf
    return metrics.ball_measure(dim, max(b, 0.0))


def ball_in_shrunk(c, dim, p, r, t, clip=None):
    """|B(p, r) ∩ C_t| (C_t clipped at ``clip``): 1D an interval, 2D a box's disc ∩ rectangle
    (closed form), a sphere's lens (closed form); 3D a box's or cylinder's by the slices along z,
    int |disc(sqrt(r^2 - z^2)) ∩ slice of C_t| dz, the slice's area closed form (a rectangle's,
    ``disc_in_rectangle``; a circle's lens, ``disc_outside_circle``), by ``_smooth_pieces`` over
    the pieces between the heights where the slice's disc meets a side, a corner or the circle."""
    b = shrunk(c, dim, t, clip)
    if c.kind == "sphere":
        if b <= 0.0:
            return 0.0
        dist = math.sqrt(sum((float(p[k]) - float(c.centre[k])) ** 2 for k in range(dim)))
        return metrics.intersection(dim, dist, r, b)
    if c.kind == "box":
        lo, hi = b[0] - np.asarray(p[:dim], float), b[1] - np.asarray(p[:dim], float)  # about the centre
        if (hi <= lo).any() or (lo >= r).any() or (hi <= -r).any():
            return 0.0
        if (lo <= -r).all() and (hi >= r).all():
            return metrics.ball_measure(dim, r)
        if dim == 1:
            return min(hi[0], r) - max(lo[0], -r)
        if dim == 2:
            return float(disc_in_rectangle(np.array([r]), lo[0], hi[0], lo[1], hi[1])[0])
        edges = [float(v) for v in (lo[0], hi[0], lo[1], hi[1])]
        corners = [ex * ex + ey * ey for ex in edges[:2] for ey in edges[2:]]
        breaks = [math.sqrt(r * r - e2) for e2 in [e * e for e in edges] + corners if e2 < r * r]
        breaks += [-v for v in breaks]
        return _smooth_pieces(lambda z: disc_in_rectangle(np.sqrt(np.maximum(r * r - z * z, 0.0)), *edges),
                              max(float(lo[2]), -r), min(float(hi[2]), r), breaks)
    radius, floor, top = b
    z_lo, z_hi = max(floor - float(p[2]), -r), min(top - float(p[2]), r)
    if radius <= 0.0 or z_hi <= z_lo:
        return 0.0
    rho = math.hypot(float(p[0]) - float(c.centre[0]), float(p[1]) - float(c.centre[1]))
    if rho >= radius + r:
        return 0.0
    if rho + r <= radius and z_lo <= -r and z_hi >= r:
        return metrics.ball_measure(3, r)
    breaks = [math.sqrt(r * r - e * e) for e in (radius - rho, radius + rho) if abs(e) < r]
    breaks += [-v for v in breaks]

    def inside(z):
        a = np.sqrt(np.maximum(r * r - z * z, 0.0))
        return np.maximum(math.pi * a * a - disc_outside_circle(a, radius, rho), 0.0)
    return _smooth_pieces(inside, z_lo, z_hi, breaks)


def nearest_wall_distances(c, dim, x, clip=None):
    """(m,) each centre's distance to its nearest wall (min_w s_iw), and (m,) bool: the centre
    lies below the clip height (the profile's region)."""
    s = gaps(c.walls, x) if len(x) else np.zeros((0, c.walls.shape[0]))
    near = s.min(axis=1) if len(x) else np.zeros(0)
    below = np.ones(len(x), bool) if clip is None else x[:, dim - 1] <= clip
    return near, below


def nearest_wall_profile(comm, c, dim, x, diam, edges, clip=None):
    """The profile from the nearest wall: (covered (K,), shell (K,), centres (K,) int) with
    covered_q = sum_i |B_i ∩ C_q| - |B_i ∩ C_q+1| (C_q the container shrunk by edges_q and
    clipped, ``ball_in_shrunk``; exact sums), shell_q = |C_q| - |C_q+1| and centres_q the centres
    below the clip whose nearest wall lies in [edges_q, edges_q+1). Each sphere's numbers from
    itself alone: the same bits on any rank count."""
    nbins = len(edges) - 1
    width = float(edges[1] - edges[0])
    r = 0.5 * np.asarray(diam, float)
    near, below = nearest_wall_distances(c, dim, x, clip)
    kc = np.floor(near / width).astype(np.int64)
    ok = below & (near >= 0) & (kc < nbins)
    centres = np.bincount(kc[ok], minlength=nbins)[:nbins]
    cols, vals = [], []
    for i in np.flatnonzero(near - r < float(edges[-1])):
        ri, mi = float(r[i]), float(near[i])
        if clip is not None and float(x[i, dim - 1]) - ri >= clip:
            continue
        # |B_i ∩ C_t| is constant for t <= m_i - r_i (only the clip cuts it) and 0 from m_i + r_i
        q0 = max(int(np.searchsorted(edges, mi - ri, side="right")) - 1, 0)
        q1 = min(int(np.searchsorted(edges, mi + ri, side="left")), nbins)
        g = [ball_in_shrunk(c, dim, x[i], ri, float(edges[q]), clip) for q in range(q0, q1 + 1)]
        for q in range(q0, q1):
            cols.append(q)
            vals.append(max(g[q - q0] - g[q - q0 + 1], 0.0))
    covered = binned_sum(comm, cols, vals, nbins)
    shell = np.array([shrunk_measure(c, dim, float(edges[q]), clip) - shrunk_measure(c, dim, float(edges[q + 1]), clip)
                      for q in range(nbins)])
    return covered, shell, halo.total(comm, centres)
