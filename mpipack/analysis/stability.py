"""The stability mathematics of ``mpipack check``: whether a scene's fixed parameters make a
stable iteration, from formulas and small eigenvalue problems (nothing here iterates the
solver).

Stability of two free spheres
-----------------------------
The paper's section 3 fixes one sphere at the origin. With both spheres free under
W = 1/(2N) sum |X_i - X_j|^2 (N = 2) the relative coordinate r = X_1 - X_2 feels grad_1 W -
grad_2 W = r (each sphere is pulled by r/2) and the constraint gradients add:
grad_1 phi - grad_2 phi = -4 r (S, phi = d^2 - r^2) or -2 r/|r| (NS, phi = d - |r|).
The fixed point is r = d with lambda* = 1/4 (S) or d/2 (NS). With y = r - d, mu = lambda -
lambda* (1D; the transverse and centre-of-mass modes are neutral: rotation and translation).

ODE (2.9), gamma form (gamma^2 = alpha beta is (2.9) itself), state (y, y', mu):

    S:   s^3 + c s^2 + 2 gamma^2 d^2 s + 8 alpha^2 beta d^2      Routh-Hurwitz: c gamma^2 > 4 alpha^2 beta
    NS:  s^3 + c s^2 + (alpha^2 + gamma^2 d) s + 2 alpha^2 beta    c (alpha^2 + gamma^2 d) > 2 alpha^2 beta

(one sphere fixed, the paper's Lemmas 3.5/3.6: c gamma^2 > 2 alpha^2 beta, i.e. c > 2 alpha,
and c (alpha^2 + gamma^2 d) > alpha^2 beta.) With gamma^2 = alpha beta, S asks c > 4 alpha.
AHA (2.7): S  s^2 + 8 alpha beta d^2 (a centre for every alpha, beta: never asymptotically
stable); NS  s^2 + alpha s + 2 alpha beta (always stable). NAP/NAV inner loops (A.1-A.3, both
spheres free): s^2 + alpha s + alpha beta g (NAV: alpha tau^2 beta g), always stable.

Discrete scheme (2.10) as the kernel runs it, lambda^n = max(0, lambda^{n-1} + beta phi(X^n))
then X^{n+1}; linearised in (y^n, y^{n-1}, mu^{n-1}), with h = 1 + c/2, a3 = alpha^2/h,
a4 = gamma^2/h, m = (1 - c/2)/h (the momentum):

    y^{n+1} = (1 + m - K - q) y^n - m y^{n-1} + G mu^{n-1},   mu^n = mu^{n-1} - (q/G) y^n

    characteristic polynomial  P(z) = z^3 + (q + K - 2 - m) z^2 + (1 + 2m - K) z - m

    S:  K = 2 a4 d^2 (the S form's lambda Hess phi cancels Hess W exactly), q = 8 a3 beta d^2
    NS: K = a3 + a4 d,                                                    q = 2 a3 beta

K is the contact's stiffness per iteration, q its dual gain. The same polynomial serves AHA
(m = 0, a3 = alpha, a4 = 0: S K = 0, q = 8 alpha beta d^2; NS K = alpha, q = 2 alpha beta) and
the inner loops of NAP (K = alpha, q = alpha beta g) and NAV (K = alpha, q = alpha tau^2 beta g),
g = |grad_1 phi - grad_2 phi|^2 of the linearised constraint (8 d^2 S, 2 NS).
For c = 2 (m = 0): stable iff 0 < K < 2 and 2K + q < 4, and then |z|^2 = 1 - K when the roots
are complex. The ODE and the scheme disagree at the step sizes that are used: the paper's
N = 2000 parameters (gamma^2 << alpha beta) fail the ODE test by three decades and are stable
as a scheme (rate K/2 per iteration); alpha = 0.35, beta = 4 passes the ODE test and is
unstable as a scheme. The verdict uses the scheme (it is what runs).

N spheres
---------
Two free spheres are the whole story for N = 2 only. For small N in 1D and 2D (2 b N +
contacts <= PATCH_MAX_SIZE, N up to about 100 in 2D) the verdict is the spectral radius of the
scheme (2.10) linearised, exactly as above but with every sphere and every contact, at the
close-packed cluster of N spheres (the N lattice points nearest the origin, multipliers of
(2.4) by least norm; rigid motions and self-stresses are neutral and left out). It includes
the stiffness, the dual gain, the pre-stress (buckling) and the momentum, and it matches runs:
7 DAHA-S discs (alpha = 0.04, beta = 0.15) certify at alpha/gamma = 0.89 and not at 1.0, the
cluster's radius crosses 1 between them (0.99993 at gamma = 0.045, 1.00006 at 0.04); at N = 100
gamma = 0.0775 certifies and 0.065 does not, the cluster is stable at 0.0775 and not at 0.07.
It is conservative for momentum at N = 100 (c = 1: radius 1.0002, the run certifies). Not in 3D:
the FCC cluster of N points is often not a local minimum (cuboctahedron -> icosahedron).

For larger N, and in 3D, the verdict uses what the project's research measured
(research/FINDINGS.md sections 1-2, refined here), and in 2D also the cluster of the largest N
that is solved exactly:

* stiffness: the step is stable only while the largest eigenvalue of alpha^2 Hess L +
  gamma^2 J^T Lambda J stays below 4 for 0 < c <= 2 (heavy ball). The multipliers grow with the
  pressure ~ R^2: the mean-field row stiffness s = sum_j lambda_ij |grad phi_ij|^2 at the
  centre of a packing of radius R = d/2 (N/phi)^(1/b) (phi = 1, 0.85, 0.64) is 2 b R^2 (S) or
  b R^2 / d (NS) (hydrostatic pressure n R^2/2 and the virial). The largest eigenvalue of
  J^T Lambda J, measured on packings made by mpipack run (`KAPPA_POINTS`), is kappa(N) times
  that: 0.5-0.65 at N = 7, 1.1-1.2 at 100 (nearly crystalline), 1.4 at 300, 4.5 at 1000 and
  5.2-6.4 at 2000 in 2D (force chains; it grows as the packing compacts), 1.8-2.1 at 2000 in
  3D; Gershgorin (2 max_i s_i) overestimates it by 1.35-2.2x. The stiffest mode is then a force
  chain, whose dual gain is 4 |grad phi|^2 per iteration x alpha^2 beta / h; K and q of that mode
  go into the same cubic. Measured on the default scene (largest eigenvalue of the dumped
  state): at iteration 5500 the cubic's radius is < 1, at 5840 > 1, and the first overlap burst
  > 1e-2 d comes at 5856; with alpha = 5.46e-3 the radius is > 1 at 10930 and the first burst
  comes at 10937; the window the check suggests for the default scene (alpha = 6.26e-3,
  gamma = 1.34e-2) ran 25000 iterations without a burst above 3e-2 d.
* buckling (b >= 2): the pre-stress lambda Hess phi is negative and only the augmentation
  braces it: alpha/gamma must stay below about 0.5-0.9 (measured: N = 7 converges at 0.89 and
  not at 1; N = 100 at 0.52 and not at 0.62; N = 2000 at 0.49, research). AHA has no
  augmentation: never stable in 2D/3D (the paper's Table 2).
* NAP/NAV: the inner loop is AHA on linearised constraints (convex, no pre-stress): the cubic
  with K = alpha and q = alpha beta g_max (NAV: alpha tau^2 beta g_max), g_max the largest
  eigenvalue of J^T J of the close-packed cluster of N spheres (computed here; 4, 6, 8
  |grad phi|^2 for large N in 1D, 2D, 3D; 4.27 for the 7-disc hexagon).
* momentum (c < 2) is reported, not judged: weakly loaded contacts are unstable when
  q > (1 - m) K (research section 2.2); measured: DAHA-NS at N = 100 certified with c = 1 and
  0.5, not 0.2; at N = 7 with c = 1, not 0.5; at N = 2000 no c < 2 tried certified.
"""

import math

import numpy as np

# close-packed fractions of the packed state (research section 3: phi_p)
PACKING_FRACTION = {1: 1.0, 2: 0.85, 3: 0.64}
# kissing numbers of the close-packed lattices (chain, triangular, FCC)
CONTACTS = {1: 2, 2: 6, 3: 12}
# largest eigenvalue of J^T Lambda J over the mean-field centre row stiffness (with R from
# PACKING_FRACTION), measured on packings made by ``mpipack run`` (power iteration on the
# dumped lambda > 0 pairs): 2D NS N = 7 (0.51-0.63 over 5 seeds), NS N = 100 (1.08),
# S N = 100 (1.18), S N = 300 (1.38), N = 1000 (4.46 after 12000 iterations), N = 2000 (5.2 at
# the onset of the bursts of the default scene, 6.4 at the onset with alpha = 5.46e-3: it
# grows as the packing compacts); 3D S N = 2000 (1.81 after 1e4 iterations, 2.08 after 4e4);
# 1D: a chain's zone-boundary mode, 4 lambda_max |grad phi|^2 = 2 s_max (theory).
KAPPA_POINTS = {1: ((2, 2.0), (1e9, 2.0)),
                2: ((2, 0.65), (7, 0.65), (100, 1.2), (300, 1.4), (1000, 4.5), (2000, 6.4), (1e9, 6.4)),
                3: ((2, 0.65), (7, 0.65), (300, 1.3), (2000, 2.1), (1e9, 2.1))}
# dual gain of the stiffest (force-chain) mode, in units of |grad phi|^2: a chain's zone
# boundary mode
CHAIN_DUAL_GAIN = 4.0
# alpha/gamma above which the pre-stress buckles the packing (DAHA, b >= 2), by N: measured
# N = 7: converges at 0.89, not at 1.0; N = 100: at 0.52, not at 0.62; N = 2000: 0.49 fine
# (research: 1.0 unstable with c = 2)
BUCKLING_POINTS = ((3, 0.9), (7, 0.9), (100, 0.55), (2000, 0.5), (1e9, 0.5))
# a pair-row entry: partner index (int32) + lambda (float64)
TOL = 1e-12


# ---- small numerics ---------------------------------------------------------------------------
def _loglinear(points, n):
    """Piecewise linear interpolation in log N through (N, value) points."""
    n = max(float(n), points[0][0])
    for (n0, v0), (n1, v1) in zip(points, points[1:]):
        if n <= n1:
            t = (math.log(n) - math.log(n0)) / (math.log(n1) - math.log(n0))
            return v0 + t * (v1 - v0)
    return points[-1][1]


def cubic_roots(K, q, m):
    """Roots of P(z) = z^3 + (q + K - 2 - m) z^2 + (1 + 2m - K) z - m: the eigenvalues of the
    linearised contact map in (y^n, y^{n-1}, mu^{n-1})."""
    return np.roots([1.0, q + K - 2.0 - m, 1.0 + 2.0 * m - K, -m])


def spectral_radius(K, q, m):
    return float(np.max(np.abs(cubic_roots(K, q, m))))


def contact_matrix(K, q, m, G=1.0):
    """The linearised map (y^n, y^{n-1}, mu^{n-1}) -> (y^{n+1}, y^n, mu^n) itself, with coupling
    G of mu into y (its eigenvalues do not depend on G)."""
    return np.array([[1.0 + m - K - q, -m, G], [1.0, 0.0, 0.0], [-q / G, 0.0, 1.0]])


def _gammainc_lower(b, x):
    """Regularised lower incomplete gamma P(b/2, x) for b = 1, 2, 3 (chi^2 with b degrees of
    freedom below 2x)."""
    if x <= 0:
        return 0.0
    if b == 1:
        return math.erf(math.sqrt(x))
    if b == 2:
        return -math.expm1(-x)
    return math.erf(math.sqrt(x)) - 2.0 * math.sqrt(x / math.pi) * math.exp(-x)


# ---- the methods' coefficients ----------------------------------------------------------------
def contact_gains(method, form, alpha, beta, gamma, c, tau=0.1, d=1.0, g_scale=None):
    """(K, q, m) of the contact mode of two free spheres at their fixed point (see the module
    docstring). ``g_scale``: for N spheres, the dual gain of the mode in units of
    |grad phi_k|^2 (default: two free spheres, 2)."""
    g1 = 4.0 * d * d if form == "S" else 1.0  # |grad_1 phi|^2 at the fixed point
    g = (2.0 if g_scale is None else g_scale) * g1
    if method == "daha":
        h = 1.0 + 0.5 * c
        a3, a4, m = alpha * alpha / h, gamma * gamma / h, (1.0 - 0.5 * c) / h
        if form == "S":
            K = 2.0 * a4 * d * d
        else:
            K = a3 + a4 * d
        return K, a3 * beta * g, m
    if method == "aha":
        return (0.0 if form == "S" else alpha), alpha * beta * g, 0.0
    if method == "nap":
        return alpha, alpha * beta * g, 0.0
    if method == "nav":
        return alpha, alpha * tau * tau * beta * g, 0.0
    raise ValueError(f"unknown method {method!r}")


def ode_polynomial(method, form, alpha, beta, gamma, c, tau=0.1, d=1.0, fixed_sphere=False):
    """Coefficients (highest first) of the characteristic polynomial of the linearised ODE of
    two spheres, both free (default) or one fixed at the origin as in the paper's section 3
    (there W's gradient is X: grad_X W = X)."""
    if method == "daha":
        if form == "S":
            k, p = 2.0 * gamma ** 2 * d * d, (4.0 if fixed_sphere else 8.0) * alpha ** 2 * beta * d * d
        else:
            k, p = alpha ** 2 + gamma ** 2 * d, (1.0 if fixed_sphere else 2.0) * alpha ** 2 * beta
        return [1.0, c, k, p]
    f = 1.0 if fixed_sphere else 2.0
    if method == "aha":
        if form == "S":
            return [1.0, 0.0, f * 4.0 * alpha * beta * d * d]
        return [1.0, alpha, f * alpha * beta]
    g1 = 4.0 * d * d if form == "S" else 1.0
    if method == "nap":
        return [1.0, alpha, f * alpha * beta * g1]
    return [1.0, alpha, f * alpha * tau * tau * beta * g1]


def ode_condition(method, form, alpha, beta, gamma, c, d=1.0, fixed_sphere=False):
    """(text, lhs, rhs, ok) of the Routh-Hurwitz condition of the ODE polynomial."""
    coef = ode_polynomial(method, form, alpha, beta, gamma, c, d=d, fixed_sphere=fixed_sphere)
    if len(coef) == 4:
        _, c2, c1, c0 = coef
        text = {"S": "c gamma^2 > {f} alpha^2 beta", "NS": "c (alpha^2 + gamma^2 d) > {f} alpha^2 beta"}[form]
        f = (2 if fixed_sphere else 4) if form == "S" else (1 if fixed_sphere else 2)
        lhs, rhs = (c * gamma ** 2, f * alpha ** 2 * beta) if form == "S" else (c * c1, c0)
        return text.format(f=f), lhs, rhs, bool(c2 > 0 and c1 > 0 and c0 > 0 and c2 * c1 > c0)
    _, c1, c0 = coef
    return "alpha > 0 (damping of the 2x2 system)", c1, 0.0, bool(c1 > 0 and c0 > 0)


# ---- N spheres: the packed state ----------------------------------------------------------------
def packing_radius(n, dim, d=1.0):
    return 0.5 * d * (n / PACKING_FRACTION[dim]) ** (1.0 / dim)


def centre_row_stiffness(n, dim, form, d=1.0):
    """Mean-field sum_j lambda_ij |grad phi_ij|^2 at the centre of the packed state."""
    R = packing_radius(n, dim, d)
    return 2.0 * dim * R * R if form == "S" else dim * R * R / d


def kappa(n, dim):
    return _loglinear(KAPPA_POINTS[dim], n)


def buckling_ratio(n):
    return _loglinear(BUCKLING_POINTS, n)


_LATTICE_GAIN = {}


def lattice_dual_gain(n, dim):
    """Largest eigenvalue of J^T J of the contact network of the N points of the close-packed
    lattice nearest the origin, in units of |grad phi|^2 (power iteration; N capped at 2000,
    where it is within a few percent of the infinite lattice's 2 z / b)."""
    key = (min(int(n), 2000), dim)
    if key in _LATTICE_GAIN:
        return _LATTICE_GAIN[key]
    m = key[0]
    if m < 2:
        return 0.0
    from mpipack.engine.initial import lattice_points
    x = lattice_points(m, dim, 1.0)
    i_list, j_list = [], []
    for lo in range(0, m, 256):  # pairs at distance 1, in blocks (m <= 2000)
        dd = np.sqrt(((x[lo:lo + 256, None, :] - x[None, :, :]) ** 2).sum(-1))
        ii, jj = np.nonzero(np.abs(dd - 1.0) < 1e-6)
        ii = ii + lo
        keep = ii < jj
        i_list.append(ii[keep])
        j_list.append(jj[keep])
    i, j = np.concatenate(i_list), np.concatenate(j_list)
    e = x[i] - x[j]
    e /= np.linalg.norm(e, axis=1)[:, None]
    v = np.random.default_rng(0).standard_normal(x.shape)
    ev = 0.0
    for _ in range(2000):
        t = ((v[i] - v[j]) * e).sum(axis=1)
        w = np.zeros_like(v)
        np.add.at(w, i, t[:, None] * e)
        np.add.at(w, j, -t[:, None] * e)
        new = float(np.linalg.norm(w))
        if new == 0.0:
            break
        v = w / new
        if abs(new - ev) <= 1e-10 * new:
            ev = new
            break
        ev = new
    _LATTICE_GAIN[key] = ev
    return ev


def packed_state(scene):
    """The N > 2 estimate: dict of the conditions, each with value, limit, ok and a text."""
    m = scene.method
    b, n, form = scene.dim, scene.n, m.form
    d = scene.particles.d_mean
    g1 = 4.0 * d * d if form == "S" else 1.0
    s_c = centre_row_stiffness(n, b, form, d)
    kap = kappa(n, b)
    k_est = kap * s_c
    omega_lat = lattice_dual_gain(n, b)
    out = {"R": packing_radius(n, b, d), "s_centre": s_c, "kappa": kap, "k_est": k_est,
           "omega_lattice": omega_lat, "conditions": []}
    conds = out["conditions"]
    if m.name == "daha":
        h = 1.0 + 0.5 * m.c
        mom = (1.0 - 0.5 * m.c) / h
        omega = min(CHAIN_DUAL_GAIN, omega_lat)
        K = (m.alpha ** 2 + m.gamma ** 2 * k_est) / h
        q = m.alpha ** 2 * m.beta * omega * g1 / h
        rho = spectral_radius(K, q, mom)
        out.update(K=K, q=q, omega=omega)
        conds.append({"name": "stiffness", "value": rho, "limit": 1.0, "ok": rho < 1.0 - TOL,
                      "text": f"stiffest mode of the packed state (force chain): alpha^2 + gamma^2 k = "
                              f"{m.alpha ** 2 + m.gamma ** 2 * k_est:.3g} (< 4 needed for c <= 2), K = {K:.3g}, "
                              f"dual gain q = {q:.3g}: spectral radius {rho:.6f}"})
        if b >= 2 and n >= 3:
            ratio = m.alpha / m.gamma if m.gamma > 0 else math.inf
            lim = buckling_ratio(n)
            conds.append({"name": "buckling", "value": ratio, "limit": lim, "ok": ratio <= lim,
                          "text": f"pre-stress braced by the augmentation: alpha/gamma = {ratio:.3g} "
                                  f"(<= {lim:.2f} at this N; 0.5 is safe at any N)"})
    elif m.name == "aha":
        if b >= 2:
            conds.append({"name": "buckling", "value": math.inf, "limit": 0.0, "ok": False,
                          "text": "AHA has no augmentation term: the pre-stress lambda Hess phi of a "
                                  "2D/3D packing is not braced (the paper's Table 2: AHA never "
                                  "converges in 2D)"})
        K, q, _ = contact_gains("aha", form, m.alpha, m.beta, m.gamma, m.c, m.tau, d, g_scale=omega_lat)
        rho = spectral_radius(K, q, 0.0)
        conds.append({"name": "contact", "value": rho, "limit": 1.0, "ok": rho < 1.0 - TOL,
                      "text": f"contacts of the packed state: K = {K:.3g}, q = {q:.3g} "
                              f"(dual gain {omega_lat:.3g} |grad phi|^2): spectral radius {rho:.6f}"})
    else:
        K, q, _ = contact_gains(m.name, form, m.alpha, m.beta, m.gamma, m.c, m.tau, d, g_scale=omega_lat)
        rho = spectral_radius(K, q, 0.0)
        out.update(K=K, q=q, omega=omega_lat)
        conds.append({"name": "inner loop", "value": rho, "limit": 1.0, "ok": rho < 1.0 - TOL,
                      "text": f"inner loop on the linearised constraints of the packed state: K = {K:.3g}, "
                              f"q = {q:.3g} (largest J^T J eigenvalue of the close-packed cluster "
                              f"{omega_lat:.3g} |grad phi|^2): spectral radius {rho:.6f}"})
    return out


# ---- N spheres: the scheme linearised at the close-packed cluster ------------------------------
# largest eigenvalue problem solved exactly: 2 b N + contacts rows (about 0.3 s at 700 on this
# machine's one core); above it the packed-state estimate is used
PATCH_MAX_SIZE = 700
_PATCH = {}


def patch_size(n, dim):
    return (2 * dim + CONTACTS[dim] // 2) * n


def cluster(n, dim, form, d=1.0):
    """The N points of the close-packed lattice nearest the origin at spacing d (every touching
    pair a contact) and the multipliers that make it a KKT point of (2.4): least-norm on the
    contacts, contacts that would pull dropped (they stay in J with lambda = 0: closed, without
    load). Returns a dict of the matrices the linearised schemes need (cached)."""
    key = (n, dim, form, d)
    if key in _PATCH:
        return _PATCH[key]
    from mpipack.engine.initial import lattice_points
    x = lattice_points(n, dim, d)
    x = x - x.mean(axis=0)
    dist = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(-1))
    i, j = np.nonzero(np.triu(np.abs(dist - d) < 1e-9 * d, 1))
    C, nb = len(i), dim * n
    r = x[i] - x[j]
    e = r / np.linalg.norm(r, axis=1)[:, None]
    J = np.zeros((C, nb))
    for k in range(C):
        gi = -2.0 * r[k] if form == "S" else -e[k]
        J[k, dim * i[k]:dim * i[k] + dim] = gi
        J[k, dim * j[k]:dim * j[k] + dim] = -gi
    gW = x.ravel()
    keep = np.ones(C, bool)
    lam = np.zeros(C)
    for _ in range(100):
        lam = np.zeros(C)
        if keep.any():
            lam[keep] = np.linalg.lstsq(J[keep].T, -gW, rcond=None)[0]
        if lam.min() >= 0:
            break
        keep &= lam > 0
    residual = float(np.linalg.norm(J.T @ lam + gW) / max(np.linalg.norm(gW), 1e-300))
    HW = np.kron(np.eye(n) - 1.0 / n, np.eye(dim))
    Hp = np.zeros((nb, nb))
    for k in range(C):
        if lam[k] == 0:
            continue
        blk = -2.0 * np.eye(dim) if form == "S" else -(np.eye(dim) - np.outer(e[k], e[k])) / d
        a, b_ = dim * i[k], dim * j[k]
        Hp[a:a + dim, a:a + dim] += lam[k] * blk
        Hp[b_:b_ + dim, b_:b_ + dim] += lam[k] * blk
        Hp[a:a + dim, b_:b_ + dim] -= lam[k] * blk
        Hp[b_:b_ + dim, a:a + dim] -= lam[k] * blk
    rank = int(np.linalg.matrix_rank(J)) if C else 0
    out = {"n": n, "dim": dim, "contacts": C, "J": J, "JtJ": J.T @ J, "JtLJ": J.T @ (lam[:, None] * J),
           "HW": HW, "Hp": Hp, "lam": lam, "residual": residual,
           # rigid motions (translation, rotation) and multipliers in ker J^T (self-stresses) are
           # fixed directions of every scheme here: eigenvalue 1, neither growing nor decaying
           "neutral": dim + dim * (dim - 1) // 2 + (C - rank) if dim > 1 else 1 + (C - rank)}
    _PATCH[key] = out
    return out


def cluster_map(P, method, alpha, beta, gamma, c, tau=0.1):
    """The linearised scheme at the cluster's KKT point as a matrix on (dX^n, dX^{n-1},
    dlambda^{n-1}) (DAHA/AHA) or (dY^n, dlambda^{n-1}) (NAP/NAV inner loop)."""
    nb, C = P["dim"] * P["n"], P["contacts"]
    J, I = P["J"], np.eye(nb)
    if method in ("daha", "aha"):
        if method == "daha":
            h = 1.0 + 0.5 * c
            m, a3, a4 = (1.0 - 0.5 * c) / h, alpha * alpha / h, gamma * gamma / h
        else:
            m, a3, a4 = 0.0, alpha, 0.0
        A = (1.0 + m) * I - a3 * (P["HW"] + P["Hp"]) - a4 * P["JtLJ"] - a3 * beta * P["JtJ"]
        M = np.zeros((2 * nb + C, 2 * nb + C))
        M[:nb, :nb] = A
        M[:nb, nb:2 * nb] = -m * I
        M[:nb, 2 * nb:] = -a3 * J.T
        M[nb:2 * nb, :nb] = I
        M[2 * nb:, :nb] = beta * J
        M[2 * nb:, 2 * nb:] = np.eye(C)
        return M
    if method == "nap":  # Y^{n+1} = Y - alpha (grad W(Y) + sum lambda grad phi^p)
        A, G = I - alpha * P["HW"] - alpha * beta * P["JtJ"], -alpha * J.T
    else:  # NAV, Y = X^p + tau V: Y^{n+1} = (1 - alpha) Y + ... - alpha tau^2 sum lambda grad phi^p
        A, G = (1.0 - alpha) * I - alpha * tau * tau * beta * P["JtJ"], -alpha * tau * tau * J.T
    M = np.zeros((nb + C, nb + C))
    M[:nb, :nb] = A
    M[:nb, nb:] = G
    M[nb:, :nb] = beta * J
    M[nb:, nb:] = np.eye(C)
    return M


def cluster_radius(P, method, alpha, beta, gamma, c, tau=0.1):
    """Spectral radius of the linearised scheme at the cluster, its neutral directions left out
    (the eigenvalues nearest 1, as many as there are neutral directions; NAP's translation is one
    more of them, NAV's inner loop has none from W)."""
    z = np.linalg.eigvals(cluster_map(P, method, alpha, beta, gamma, c, tau))
    k = P["neutral"]
    if method == "nav":
        k -= P["dim"] + P["dim"] * (P["dim"] - 1) // 2 if P["dim"] > 1 else 1
    elif method == "nap" and P["dim"] > 1:
        k -= P["dim"] * (P["dim"] - 1) // 2  # linearised constraints: rotations are not free
    order = np.argsort(np.abs(z - 1.0))
    rest = z[order[max(k, 0):]]
    return float(np.max(np.abs(rest))) if rest.size else 0.0


# ---- the verdict ------------------------------------------------------------------------------------
def two_spheres(scene):
    """Two free spheres (exact for N = 2): the ODE and the discrete map."""
    m = scene.method
    if scene.n == 2:
        from mpipack.engine.initial import scene_diameters
        dd = scene_diameters(scene, np.arange(2, dtype=np.int64))
        d = float(0.5 * (dd[0] + dd[1]))
    else:
        d = scene.particles.d_mean
    K, q, mom = contact_gains(m.name, m.form, m.alpha, m.beta, m.gamma, m.c, m.tau, d)
    z = cubic_roots(K, q, mom)
    rho = float(np.max(np.abs(z)))
    ode = ode_polynomial(m.name, m.form, m.alpha, m.beta, m.gamma, m.c, m.tau, d)
    s = np.roots(ode)
    cond = ode_condition(m.name, m.form, m.alpha, m.beta, m.gamma, m.c, d) if m.name in ("daha", "aha") else None
    paper = ode_condition(m.name, m.form, m.alpha, m.beta, m.gamma, m.c, d, fixed_sphere=True) \
        if m.name == "daha" else None
    lam = 0.25 if m.form == "S" else d / 2.0
    return {"d": d, "lambda": lam, "K": K, "q": q, "m": mom, "z": z, "rho": rho,
            "ok": rho < 1.0 - TOL, "ode": ode, "ode_roots": s,
            "ode_ok": bool(np.max(s.real) < -TOL), "ode_condition": cond, "paper_condition": paper}


def with_param(scene, key, value):
    """The scene with method.<key> = value; a gamma left to its default sqrt(alpha beta) follows
    alpha and beta, as it would with --set."""
    m = scene.method
    change = {key: value}
    if key in ("alpha", "beta") and m.gamma > 0 and abs(m.gamma - math.sqrt(m.alpha * m.beta)) <= 1e-12 * m.gamma:
        a = value if key == "alpha" else m.alpha
        b = value if key == "beta" else m.beta
        change["gamma"] = math.sqrt(a * b)
    return scene.replace(method=change)


def cluster_n(scene):
    """The largest N' <= N whose cluster problem is small enough to solve exactly; 0 in 3D,
    where the FCC cluster of N points is often not a local minimum of W (the 13-sphere
    cuboctahedron turns into an icosahedron): its eigenvalues would judge the cluster, not the
    parameters (measured: radius 1.0005 for N = 13 whatever gamma is)."""
    if scene.dim == 3:
        return 0
    n = scene.n
    while n > 2 and patch_size(n, scene.dim) > PATCH_MAX_SIZE:
        n = int(n * 0.9)
    return n


def cluster_condition(scene, n=None):
    """The linearised scheme at the close-packed cluster of n spheres (default: the scene's N)."""
    m = scene.method
    n = scene.n if n is None else n
    d = scene.particles.d_mean
    P = cluster(n, scene.dim, m.form, d)
    rho = cluster_radius(P, m.name, m.alpha, m.beta, m.gamma, m.c, m.tau)
    what = "the inner loop (linearised constraints) " if m.nested else "the scheme "
    return {"name": "cluster" if n == scene.n else f"cluster of {n}", "value": rho, "limit": 1.0,
            "ok": rho < 1.0 - TOL and P["residual"] < 1e-8,
            "text": f"{what}linearised at the close-packed cluster of {n} spheres ({P['contacts']} contacts, "
                    f"multipliers {P['lam'].min():.3g}-{P['lam'].max():.3g}, KKT residual {P['residual']:.1e}): "
                    f"spectral radius {rho:.6f} (neutral rigid motions and self-stresses left out)"}


def verdict(scene):
    """(stable, report dict). N = 2: the exact two-sphere scheme; small N: the scheme linearised
    at the close-packed cluster of N spheres; large N: the packed-state estimate and the
    cluster of the largest N that is solved exactly (N = 1 has nothing to be unstable)."""
    rep = {"two": two_spheres(scene) if scene.n >= 2 else None, "packed": None, "cluster": None}
    if scene.n == 1:
        return True, rep
    if scene.n == 2:
        return rep["two"]["ok"], rep
    nc = cluster_n(scene)
    if nc == scene.n and scene.n >= 3:
        rep["cluster"] = cluster_condition(scene)
        return rep["cluster"]["ok"], rep
    rep["packed"] = packed_state(scene)
    if nc >= 3:
        rep["cluster"] = cluster_condition(scene, nc)
        rep["packed"]["conditions"].append(rep["cluster"])
    return all(c["ok"] for c in rep["packed"]["conditions"]), rep


def _is_stable_estimate(scene):
    """The cheap part of the verdict (no cluster eigenvalues): for margins at large N."""
    if scene.n <= 2 or cluster_n(scene) >= scene.n:
        return verdict(scene)[0]
    return all(c["ok"] for c in packed_state(scene)["conditions"])


def _is_stable(scene):
    return verdict(scene)[0]
