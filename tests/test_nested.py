"""The nested methods NAP (2.16) and NAV (2.17) of Degond, Ferreira, Motsch 2017, section 2.4.

1. The inner-step kernels against numpy O(N^2) references written from the paper: (2.15) for
   the linearised constraints, (2.16) for NAP, (2.17) in its V form for NAV.
2. The outer loop of the solver (in-process, one rank) against a reference outer loop, and
   Appendix A on two spheres in 1D (Lemmas A.1, A.2, A.3).
3. Rank-count independence (mpirun -n 1/2/3, --dump, bitwise).
4. The paper's N = 7 case (Table 1 parameters): the optimum W = 3 is reached.

Two free spheres in 1D. With W = 1/(2N) sum_{i<j} |X_i - X_j|^2 (3.1), grad_{X_1} W = r/2 with
r = X_1 - X_2, so r obeys Appendix A's equations for one sphere moving against one fixed at the
origin, with the multiplier doubled: the outer iterates r_p of Appendix A are those of r, and
the multiplier of the pair is half of Appendix A's lambda*:

    NAP-NS (A.1):  r_{p+1} = d sign(r_p),                lambda^{p+1} = d / 2
    NAP-S  (A.2):  r_{p+1} = (d^2 + r_p^2) / (2 r_p),    lambda^{p+1} = (d^2 + r_p^2) / (8 r_p^2)
    NAV-NS (A.3):  r_{p+1} = d sign(r_p),                mu^{p+1} = (d - |r_p| (1 - tau)) / (2 tau^2)

A.3 needs mu^{p+1} >= 0, i.e. (1 - tau) |r_p| <= d: the constraint must be active. Further
apart, (2.2) is unconstrained and r_{p+1} = (1 - tau) r_p (V = -grad W(X^p)); so NAV's outer
map is r -> max(d, (1 - tau) r) for r > 0.
"""

import math
import zlib

import numpy as np
import pytest

from conftest import assert_bitwise_equal, describe, mpipack_run, step_each
from support import CENTRE, no_walls
from mpipack import config
from mpipack.parallel import exactsum, neighbors
from mpipack.kernels import daha as kernels
from mpipack.engine import solver
from mpipack.parallel.comm import Comm
from mpipack.methods import nested

RUN_TIMEOUT = 180  # seconds, per mpirun; healthy runs below take a few seconds


@pytest.fixture(scope="module")
def comm():
    c = Comm()
    assert c.size == 1
    return c


# ---------------------------------------------------------------------------------------------
# reference: (2.15), (2.16), (2.17) over all pairs k < l
# ---------------------------------------------------------------------------------------------


def phi_and_grad(form, xk, xl, dkl):
    """phi_kl and grad_{X_k} phi_kl at X (Definition 2.1); grad_{X_l} phi_kl is its negative."""
    diff = xk - xl
    r2 = float(diff @ diff)
    if form == "S":
        return dkl * dkl - r2, -2.0 * diff
    r = math.sqrt(r2)
    return dkl - r, -diff / r


def linearised(form, xp, y, diam):
    """(2.15) for every pair k < l: phi^p_kl(Y) = phi_kl(X^p) + grad phi_kl(X^p) . (Y - X^p),
    and grad_{X_k} phi^p_kl (= grad_{X_k} phi_kl(X^p), constant). Returns two dicts."""
    n = xp.shape[0]
    phi, grad = {}, {}
    for k in range(n):
        for l in range(k + 1, n):
            f, g = phi_and_grad(form, xp[k], xp[l], 0.5 * (diam[k] + diam[l]))
            phi[k, l] = f + float(g @ (y[k] - xp[k])) - float(g @ (y[l] - xp[l]))
            grad[k, l] = g
    return phi, grad


def constraint_sum(lam, grad, shape):
    """sum_{k<l} lambda_kl grad_{X_i} phi^p_kl, for every i."""
    s = np.zeros(shape)
    for (k, l), g in grad.items():
        s[k] += lam[k, l] * g
        s[l] -= lam[k, l] * g
    return s


def project_multipliers(lam, phi, beta):
    """(2.16b) / (2.17b): max(0, lambda + beta phi^p), symmetric matrix."""
    out = lam.copy()
    for (k, l), f in phi.items():
        out[k, l] = out[l, k] = max(0.0, lam[k, l] + beta * f)
    return out


def ref_nap_inner(form, y, xp, diam, lam, alpha, beta, update, xbar):
    """One inner step of NAP, multipliers first as the kernel does it:
    lambda^{p,n} = max(0, lambda^{p,n-1} + beta phi^p(X^{p,n})) ((2.16b) one index back, only
    if update), then (2.16a) X^{p,n+1} = X^{p,n} - alpha (grad W(X^{p,n}) + sum lambda^{p,n}
    grad phi^p). lam is lambda^{p,n-1} (lambda^{p,n} when not update). xbar = Xbar(X^{p,n})."""
    phi, grad = linearised(form, xp, y, diam)
    if update:
        lam = project_multipliers(lam, phi, beta)
    y_new = y - alpha * ((y - xbar) + constraint_sum(lam, grad, y.shape))
    return y_new, lam


def ref_nav_inner(form, v, xp, diam, mu, alpha, beta, tau, update, xbar_p):
    """One inner step of NAV in its V form: mu^{p,n} = max(0, mu^{p,n-1} + beta phi^p(X^p +
    tau V^{p,n})) (if update), then (2.17a) V^{p,n+1} = V^{p,n} - alpha (V^{p,n} + grad W(X^p)
    + tau sum mu^{p,n} grad phi^p). xbar_p = Xbar(X^p)."""
    phi, grad = linearised(form, xp, xp + tau * v, diam)
    if update:
        mu = project_multipliers(mu, phi, beta)
    v_new = v - alpha * (v + (xp - xbar_p) + tau * constraint_sum(mu, grad, v.shape))
    return v_new, mu


def ref_outer(method, form, x0, diam, alpha, beta, tau, l_inner, eps_inner, n_outer):
    """Definitions 2.5 / 2.6 with the inner loop stopped by (4.1) / (4.2) or after l_inner
    steps. Returns a list of (X^{p+1}, lambda^{p+1} matrix, inner steps) for p = 0..n_outer-1.
    lambda^0 = 0 and V^0 = 0."""
    n = x0.shape[0]
    x = x0.copy()
    lam = np.zeros((n, n))
    v = np.zeros_like(x0)
    out = []
    for _ in range(n_outer):
        xp = x.copy()
        if method == "nap":
            y = xp.copy()
            for it in range(1, l_inner + 1):
                phi, grad = linearised(form, xp, y, diam)
                y_new = y - alpha * ((y - y.mean(axis=0)) + constraint_sum(lam, grad, y.shape))
                phi, _ = linearised(form, xp, y_new, diam)
                lam = project_multipliers(lam, phi, beta)  # (2.16b)
                rel = np.linalg.norm(y_new - y) / np.linalg.norm(y)  # (4.1)
                y = y_new
                if rel < eps_inner:
                    break
            x = y
        else:
            xbar_p = xp.mean(axis=0)
            norm_p = np.linalg.norm(xp)
            for it in range(1, l_inner + 1):
                _, grad = linearised(form, xp, xp + tau * v, diam)
                v_new = v - alpha * (v + (xp - xbar_p) + tau * constraint_sum(lam, grad, v.shape))
                phi, _ = linearised(form, xp, xp + tau * v_new, diam)
                lam = project_multipliers(lam, phi, beta)  # (2.17b)
                rel = np.linalg.norm(v_new - v) / norm_p  # (4.2), compared with eps_inner / tau
                v = v_new
                if rel < eps_inner / tau:
                    break
            x = xp + tau * v
        out.append((x.copy(), lam.copy(), it))
    return out


# ---------------------------------------------------------------------------------------------
# 1. inner-step kernels
# ---------------------------------------------------------------------------------------------

KERNEL_PARAMS = {
    "nap": dict(alpha=0.3, beta=0.7, tau=0.1),
    "nav": dict(alpha=0.4, beta=40.0, tau=0.15),
}


def full_rows(x, n_local, gid, diam):
    """Pair rows from neighbors.build_rows with a skin so large that every pair is in them."""
    n = x.shape[0]
    empty = (np.zeros(n_local + 1, np.int64), np.empty(0, np.int64), np.empty(0))
    offsets, pair_j, pair_lambda, missing, _ = neighbors.build_rows(x, n_local, n, gid, diam, 1e3, *empty)
    assert missing == 0
    assert np.array_equal(np.diff(offsets), np.full(n_local, n - 1)), "rows must be complete"
    for i in range(n_local):  # sorted by partner gid
        assert np.all(np.diff(gid[pair_j[offsets[i]:offsets[i + 1]]]) > 0)
    return offsets, pair_j


def nested_setup(rng, n, dim, form):
    """X^p: a dense polydisperse Gaussian cloud; Y = X^p + noise; random multipliers > 0 on
    most pairs (overlapping or not, so that the update both keeps and clips)."""
    xp = rng.normal(size=(n, dim)) * (0.35 * n ** (1.0 / dim))
    diam = rng.uniform(0.8, 1.3, size=n)
    step = 0.2 * rng.normal(size=(n, dim))
    lam = np.zeros((n, n))
    for k in range(n):
        for l in range(k + 1, n):
            if rng.uniform() < 0.8:
                lam[k, l] = lam[l, k] = rng.uniform(0.05, 1.0) * (0.5 if form == "S" else 1.0)
    gid = rng.permutation(n).astype(np.int64)
    return xp, diam, step, lam, gid


def run_nested_kernel(method, form, y, xp, diam, offsets, pair_j, pair_lambda, xbar, p, update,
                      n_local):
    kern = kernels.nested_step(method, form)
    cy, cp, cw, cf = nested.nested_coefficients(method, p["alpha"], p["tau"])
    b = y.shape[1]
    y_new = np.full_like(y, np.nan)
    acc = exactsum.new_accumulator(b + 2)
    maxima = np.zeros(kernels.N_MAX)
    n_active = kern(y, xp, y_new, n_local, diam, offsets, pair_j, pair_lambda, *no_walls(n_local), xbar,
                    CENTRE, cy, cp, cw, cf, p["beta"], update, acc, maxima)
    return y_new, acc, maxima, n_active


def reference_inner(method, form, y, xp, diam, lam, p, update):
    """(Y^{n+1}, multipliers used) from the paper's formulas; NAV through V = (Y - X^p)/tau."""
    if method == "nap":
        return ref_nap_inner(form, y, xp, diam, lam, p["alpha"], p["beta"], update, y.mean(axis=0))
    tau = p["tau"]
    v = (y - xp) / tau
    v_new, mu = ref_nav_inner(form, v, xp, diam, lam, p["alpha"], p["beta"], tau, update,
                              xp.mean(axis=0))
    return xp + tau * v_new, mu


@pytest.mark.parametrize("update", [True, False], ids=["update", "first"])
@pytest.mark.parametrize("method", ["nap", "nav"])
@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_inner_kernel_matches_reference(dim, form, method, update):
    p = KERNEL_PARAMS[method]
    rng = np.random.default_rng(zlib.crc32(f"nested-{dim}-{form}-{method}-{update}".encode()))
    n = 20
    xp, diam, step, lam_prev, gid = nested_setup(rng, n, dim, form)
    y = xp + step
    xbar = (y if method == "nap" else xp).mean(axis=0)  # NAP: Xbar of Y; NAV: Xbar of X^p

    y_ref, lam_ref = reference_inner(method, form, y, xp, diam, lam_prev, p, update)

    offsets, pair_j = full_rows(y, n, gid, diam)
    owner = np.repeat(np.arange(n), np.diff(offsets))
    pair_lambda = lam_prev[owner, pair_j].copy()
    y_new, acc, maxima, n_active = run_nested_kernel(method, form, y, xp, diam, offsets, pair_j,
                                                     pair_lambda, xbar, p, update, n)

    assert np.allclose(y_new, y_ref, rtol=1e-12, atol=1e-12), np.abs(y_new - y_ref).max()
    assert np.allclose(pair_lambda, lam_ref[owner, pair_j], rtol=1e-12, atol=1e-12), \
        np.abs(pair_lambda - lam_ref[owner, pair_j]).max()
    if update:
        # the set-up exercises both branches of max(0, .)
        clipped = (lam_prev[owner, pair_j] > 0) & (lam_ref[owner, pair_j] == 0)
        assert clipped.any() and (lam_ref[owner, pair_j] > 0).any()
    else:
        assert np.array_equal(pair_lambda, lam_prev[owner, pair_j])
    # the two ends of a pair hold the same bits (phi^p is bitwise symmetric)
    mirror = {(owner[e], pair_j[e]): pair_lambda[e] for e in range(pair_j.shape[0])}
    assert all(mirror[i, j] == mirror[j, i] for (i, j) in mirror)
    assert n_active == np.count_nonzero(lam_ref)
    # exact sums: sum Y^{n+1} (b rows), sum |Y^{n+1} - Y^n|^2, sum |Y^n|^2
    for k in range(dim):
        assert math.isclose(exactsum.value(acc, k), math.fsum(y_ref[:, k]), rel_tol=1e-12,
                            abs_tol=1e-11)
    assert math.isclose(exactsum.value(acc, dim), math.fsum(((y_ref - y) ** 2).ravel()),
                        rel_tol=1e-10)
    assert math.isclose(exactsum.value(acc, dim + 1), math.fsum((y ** 2).ravel()), rel_tol=1e-14)
    # maxima: largest step^2, largest real overlap (d_ij - r)/d_ij at Y^n
    assert math.isclose(maxima[kernels.MAX_STEP2], ((y_ref - y) ** 2).sum(axis=1).max(),
                        rel_tol=1e-10)
    r = np.sqrt(((y[:, None, :] - y[None, :, :]) ** 2).sum(axis=2))
    dkl = 0.5 * (diam[:, None] + diam[None, :])
    ov = (dkl - r) / dkl
    np.fill_diagonal(ov, -np.inf)
    assert ov.max() > 0, "test set-up: want overlaps"
    assert math.isclose(maxima[kernels.MAX_OVERLAP], ov.max(), rel_tol=1e-12)


@pytest.mark.parametrize("method", ["nap", "nav"])
@pytest.mark.parametrize("form", ["S", "NS"])
def test_inner_kernel_with_ghosts(form, method):
    """Locals first, then ghosts (2D): the local rows of Y^{n+1} are the full system's, ghost
    rows of y_new are not written, and the kernel reads the ghosts' linearisation points."""
    p = KERNEL_PARAMS[method]
    rng = np.random.default_rng(zlib.crc32(f"ghosts-{form}-{method}".encode()))
    n, n_local = 24, 15
    xp, diam, step, lam_prev, gid = nested_setup(rng, n, 2, form)
    y = xp + step
    y_ref, lam_ref = reference_inner(method, form, y, xp, diam, lam_prev, p, True)
    offsets, pair_j = full_rows(y, n_local, gid, diam)
    owner = np.repeat(np.arange(n_local), np.diff(offsets))
    pair_lambda = lam_prev[owner, pair_j].copy()
    xbar = (y if method == "nap" else xp).mean(axis=0)
    y_new, _, _, _ = run_nested_kernel(method, form, y, xp, diam, offsets, pair_j, pair_lambda,
                                       xbar, p, True, n_local)
    assert np.allclose(y_new[:n_local], y_ref[:n_local], rtol=1e-12, atol=1e-12)
    assert np.all(np.isnan(y_new[n_local:])), "ghost rows of y_new must not be written"
    assert np.allclose(pair_lambda, lam_ref[owner, pair_j], rtol=1e-12, atol=1e-12)


def test_nested_coefficients():
    assert nested.nested_coefficients("nap", 0.3, 0.2) == (1.0, 0.0, 0.3, 0.3)
    cy, cp, cw, cf = nested.nested_coefficients("nav", 0.3, 0.2)
    assert np.allclose((cy, cp, cw, cf), (0.7, 0.3, 0.3 * 0.2, 0.3 * 0.2 ** 2), rtol=1e-15)
    with pytest.raises(ValueError):
        nested.nested_coefficients("daha", 0.3, 0.2)


# ---------------------------------------------------------------------------------------------
# 2a. the outer loop of the solver against the reference outer loop
# ---------------------------------------------------------------------------------------------

OUTER_CASES = {
    # (method, form, dim, alpha, beta, tau, l_inner, eps_inner, n_outer)
    "nap-NS-fixed": ("nap", "NS", 2, 0.3, 0.5, 0.1, 6, 0.0, 4),
    "nap-S-criterion": ("nap", "S", 2, 0.1, 0.1, 0.1, 400, 1e-5, 3),
    "nap-NS-3d-one-inner": ("nap", "NS", 3, 0.3, 0.5, 0.1, 1, 0.0, 5),
    "nav-NS-fixed": ("nav", "NS", 2, 0.4, 40.0, 0.1, 6, 0.0, 4),
    "nav-S-criterion": ("nav", "S", 2, 0.3, 2.0, 0.2, 400, 1e-6, 3),
    "nav-NS-1d": ("nav", "NS", 1, 0.4, 40.0, 0.1, 8, 0.0, 4),
}


@pytest.mark.parametrize("case", list(OUTER_CASES))
def test_outer_loop_matches_reference(comm, case):
    """The outer iteration (nested.outer_step) of NAP / NAV on one rank, every pair in the rows (large skin):
    X^{p+1}, lambda^{p+1} and the inner step counts of Definitions 2.5 / 2.6 with (4.1) /
    (4.2). Covers what the kernel test cannot: which Xbar is used, the multipliers carried from
    one outer iteration to the next (lambda^{p,0} = lambda^p), NAV's V^{p,0} = V^p, the inner
    criteria and l_inner."""
    method, form, dim, alpha, beta, tau, l_inner, eps_inner, n_outer = OUTER_CASES[case]
    n = 10
    scene = config.load("default", [
        f"dim={dim}", f"n={n}", "seed=3", "init.sigma=0.8", "particles.diameter_max=1.2",
        f"method.name={method}", f"method.form={form}", f"method.alpha={alpha}",
        f"method.beta={beta}", f"method.tau={tau}", f"method.l_inner={l_inner}",
        f"method.eps_inner={eps_inner}", "stop.eps=0"])
    scene = scene.replace(neighbor={"skin": 100.0})  # every pair in the rows (beyond a scene's bound)
    s = solver.Solver(scene, comm)
    s.initialise()
    g0 = s.gather()
    ref = ref_outer(method, form, g0["x"], g0["diam"], alpha, beta, tau, l_inner, eps_inner, n_outer)
    seen = {"total_inner": 0}

    def check(fig):
        p = fig["iteration"] - 1
        x_ref, lam_ref, inner_ref = ref[p]
        g = s.gather()
        assert fig["iteration"] == p + 1
        assert fig["inner_iterations"] == inner_ref, (p, fig["inner_iterations"], inner_ref)
        seen["total_inner"] += inner_ref
        assert s.counters["inner_iterations"] == seen["total_inner"]
        assert np.allclose(g["x"], x_ref, rtol=1e-10, atol=1e-10), (p, np.abs(g["x"] - x_ref).max())
        lam = np.zeros((n, n))
        gi, gj = g["pairs_gid"][:, 0], g["pairs_gid"][:, 1]
        lam[gi, gj] = g["pairs_lambda"]
        upper = np.triu(lam_ref, 1)
        assert np.allclose(lam, upper, rtol=1e-9, atol=1e-10), (p, np.abs(lam - upper).max())
        # (4.3) relative change of the outer iterate
        x_prev_ref = ref[p - 1][0] if p > 0 else g0["x"]
        rel = np.linalg.norm(x_ref - x_prev_ref) / np.linalg.norm(x_prev_ref)
        assert fig["relative_change"] == pytest.approx(rel, rel=1e-8)

    step_each(s, n_outer, check)
    assert s.state.iteration == n_outer
    assert np.count_nonzero(np.triu(ref[-1][1], 1)) > 3, "test set-up: want active pairs"
    if eps_inner > 0:
        assert any(r[2] < l_inner for r in ref), "test set-up: the inner criterion should stop"


# ---------------------------------------------------------------------------------------------
# 2b. Appendix A: two spheres in 1D, converged inner loops
# ---------------------------------------------------------------------------------------------

# alpha, beta for which the discrete inner loop (Arrow-Hurwicz on a convex problem) converges;
# l_inner large and eps_inner tiny: the inner loop runs until the iterate stops moving
CONVERGED_INNER = ["method.l_inner=100000", "method.eps_inner=1e-15"]


def two_spheres(comm, method, form, spacing, alpha, beta, tau=0.1, d=1.0):
    """Solver on the two-spheres scene, spheres at 0 and -spacing (r_0 = spacing)."""
    scene = config.load("two-spheres", [
        f"method.name={method}", f"method.form={form}", "init.kind=lattice",
        f"init.spacing={spacing}", f"method.alpha={alpha}", f"method.beta={beta}",
        f"method.tau={tau}", f"particles.diameter={d}"] + CONVERGED_INNER)
    s = solver.Solver(scene, comm)
    s.initialise()
    g = s.gather()
    assert g["x"][0, 0] - g["x"][1, 0] == pytest.approx(spacing, rel=1e-14)
    return s


def outer_distances(s, steps):
    """[(r_{p+1}, multiplier of the pair or 0, centre of mass, relative change (4.3))] for
    p = 0..steps-1."""
    out = []

    def record(fig):
        g = s.gather()
        lam = float(g["pairs_lambda"][0]) if g["pairs_lambda"].shape[0] else 0.0
        out.append((float(g["x"][0, 0] - g["x"][1, 0]), lam, float(g["x"].mean()),
                    fig["relative_change"]))

    step_each(s, steps, record)
    return out


@pytest.mark.parametrize("alpha,beta", [(0.5, 0.5), (0.6, 0.46), (0.2, 0.1)])
@pytest.mark.parametrize("r0", [1.7, 0.4])
def test_nap_ns_lemma_a1(comm, r0, alpha, beta):
    """Lemma A.1: NAP-NS reaches r = d after ONE outer iteration, then stays; lambda = d/2."""
    d = 1.0
    s = two_spheres(comm, "nap", "NS", r0, alpha, beta, d=d)
    hist = outer_distances(s, 3)
    for p, (r, lam, com, _) in enumerate(hist):
        assert abs(r - d) < 1e-9, (p, r)
        assert abs(lam - d / 2) < 1e-9, (p, lam)
        assert abs(com - (-r0 / 2)) < 1e-12, "the centre of mass must not move"
    assert hist[-1][3] < 1e-9, "(4.3) should fire on the second outer iteration"


@pytest.mark.parametrize("r0", [1.7, 0.4])
def test_nap_s_lemma_a2(comm, r0):
    """Lemma A.2: NAP-S outer iterates r_{p+1} = (d^2 + r_p^2) / (2 r_p), decreasing to d from
    above (r_0 > d), jumping above d first from r_0 < d; lambda^{p+1} = (d^2 + r_p^2)/(8 r_p^2)."""
    d = 1.0
    s = two_spheres(comm, "nap", "S", r0, 0.5, 0.2, d=d)
    hist = outer_distances(s, 4)
    r_prev, r_exact = r0, r0
    for p, (r, lam, com, _) in enumerate(hist):
        want = (d * d + r_prev * r_prev) / (2 * r_prev)
        assert r == pytest.approx(want, rel=1e-9, abs=1e-9), (p, r, want)
        r_exact = (d * d + r_exact * r_exact) / (2 * r_exact)
        assert r == pytest.approx(r_exact, rel=1e-8), (p, r, r_exact)
        assert lam == pytest.approx((d * d + r_prev ** 2) / (8 * r_prev ** 2), rel=1e-8), (p, lam)
        assert r > d, "every outer iterate lies above d"
        if p > 0:
            assert r < r_prev, "the sequence decreases after the first step"
        assert abs(com - (-r0 / 2)) < 1e-12
        r_prev = r
    assert 0 < hist[-1][0] - d < 1e-5  # converging, but not in one step: quadratic, from above


@pytest.mark.parametrize("r0", [0.4, 1.05])
def test_nav_ns_lemma_a3(comm, r0):
    """Lemma A.3: NAV-NS reaches r = d after one outer iteration when the constraint is active
    ((1 - tau) r_0 <= d), with mu^1 = (d - r_0 (1 - tau)) / (2 tau^2); then mu = d/(2 tau)."""
    d, tau = 1.0, 0.1
    s = two_spheres(comm, "nav", "NS", r0, 0.5, 40.0, tau=tau, d=d)
    hist = outer_distances(s, 3)
    r_prev = r0
    for p, (r, lam, com, _) in enumerate(hist):
        assert abs(r - d) < 1e-9, (p, r)
        assert lam == pytest.approx((d - r_prev * (1 - tau)) / (2 * tau * tau), rel=1e-7), (p, lam)
        assert abs(com - (-r0 / 2)) < 1e-12
        r_prev = r


def test_nav_ns_from_afar_stops_at_d(comm):
    """NAV-NS from r_0 = 1.7 > d + skin (the pair is not in the rows at the start): with a
    converged inner loop the outer map is r -> max(d, (1 - tau) r): 1.53, 1.377, 1.2393,
    1.11537, 1.003833, then d for good. The spheres must never overlap."""
    d, tau = 1.0, 0.1
    s = two_spheres(comm, "nav", "NS", 1.7, 0.5, 40.0, tau=tau, d=d)
    hist = outer_distances(s, 8)
    r_exact = 1.7
    for p, (r, lam, com, _) in enumerate(hist):
        r_exact = max(d, (1 - tau) * r_exact)
        assert r == pytest.approx(r_exact, rel=1e-9), (p, [h[0] for h in hist])
    assert hist[-1][1] == pytest.approx(d / (2 * tau), rel=1e-7)


def test_nap_ns_one_outer_iteration_on_3_ranks(tmp_path):
    """Lemma A.1 through the command line, on 3 ranks (one of them owns nothing): (4.3) stops
    at the second outer iteration, the spheres touch, lambda = d/2."""
    sets = ["method.name=nap", "method.form=NS", "init.kind=lattice", "init.spacing=1.7",
            "method.alpha=0.5", "method.beta=0.5", "stop.eps=1e-9"] + CONVERGED_INNER
    proc, s, dump = mpipack_run(3, tmp_path, "two-spheres", sets, dump=True, timeout=RUN_TIMEOUT)
    assert proc.returncode == 0, describe(proc)
    assert s is not None and dump is not None, describe(proc)
    assert s["method"] == "nap" and s["stop_reason"] == "eps" and s["converged"] is True
    assert s["iterations"] == 2, s
    assert s["inner_iterations"] > s["iterations"], s
    assert abs((dump["x"][0, 0] - dump["x"][1, 0]) - 1.0) < 1e-9
    assert dump["pairs_gid"].tolist() == [[0, 1]]
    assert abs(dump["pairs_lambda"][0] - 0.5) < 1e-9
    assert abs(s["W"] - 0.25) < 1e-9 and s["max_overlap"] < 1e-9


# ---------------------------------------------------------------------------------------------
# 3. rank-count independence
# ---------------------------------------------------------------------------------------------


RANK_CASES = {
    # (sets, outer iterations, rank counts, inner criterion must fire). Paper, Fig. 6 (N = 100):
    # (c) NAP-NS, (e) NAV-NS, (d) NAP-S. NAV-S is not in the paper (remark after Lemma A.3):
    # parameters for which it stays bounded. The first outer iterations use all l_inner = 1000
    # inner steps (about 1.5 ms each on 3 ranks here), so the counts are kept small.
    "nap-NS": (["method.name=nap", "method.form=NS", "method.alpha=0.1", "method.beta=0.16"],
               20, (1, 2, 3), True),
    "nav-NS": (["method.name=nav", "method.form=NS", "method.alpha=0.31", "method.beta=41",
                "method.tau=0.1"], 16, (1, 2, 3), True),
    "nap-S": (["method.name=nap", "method.form=S", "method.alpha=0.015", "method.beta=0.026"],
              6, (1, 3), False),
    "nav-S": (["method.name=nav", "method.form=S", "method.alpha=0.1", "method.beta=2",
               "method.tau=0.1"], 6, (1, 3), False),
}


@pytest.mark.parametrize("case", list(RANK_CASES))
def test_same_bits_on_1_2_3_ranks(run_mpipack, case):
    """2D, N = 100 from a Gaussian start, l_inner = 1000, eps_inner = 1e-9, a fixed number of
    outer iterations: positions, previous positions and multipliers bitwise equal on any
    number of ranks, and the same summary figures."""
    method_sets, n_outer, ranks, criterion_fires = RANK_CASES[case]
    sets = ["n=100", "dim=2", "method.l_inner=1000", "method.eps_inner=1e-9", "stop.eps=0",
            f"stop.max_iter={n_outer}"] + method_sets
    runs = {}
    for P in ranks:
        proc, s, d = run_mpipack(P, None, sets, dump=True, timeout=RUN_TIMEOUT)
        assert proc.returncode == 0, describe(proc)
        assert s is not None and d is not None, describe(proc)
        assert "Traceback" not in proc.stderr, describe(proc)
        assert s["ranks"] == P and s["iterations"] == n_outer, s
        assert s["method"] == method_sets[0].split("=")[1]
        assert n_outer < s["inner_iterations"] <= 1000 * n_outer, s
        if criterion_fires:  # (4.1) / (4.2), decided collectively, ended some inner loops
            assert s["inner_iterations"] < 1000 * n_outer, s
        runs[P] = (s, d)
    s1, d1 = runs[1]
    assert np.array_equal(d1["gid"], np.arange(100))
    assert d1["pairs_gid"].shape[0] > 50, "test set-up: want many contacts"
    assert s1["max_overlap"] < 0.05, s1
    assert np.all(np.isfinite(d1["x"])) and s1["W"] < 1e4, s1
    for P in ranks[1:]:
        s, d = runs[P]
        assert_bitwise_equal(d1, d, f"{case}: 1 rank vs {P} ranks")
        for key in ("W", "max_overlap", "relative_change", "active_pairs", "inner_iterations",
                    "rebuilds", "density"):
            assert s[key] == s1[key], (key, P, s[key], s1[key])
    s3 = runs[3][0]
    assert s3["rebuilds"] > 1 and s3["rebalances"] >= 1, s3


# ---------------------------------------------------------------------------------------------
# 4. the paper's N = 7 case (section 4.1, Table 1 parameters)
# ---------------------------------------------------------------------------------------------

TABLE1 = {
    "nap-NS": ["method.name=nap", "method.form=NS", "method.alpha=0.6", "method.beta=0.46"],
    "nap-S": ["method.name=nap", "method.form=S", "method.alpha=0.25", "method.beta=0.28"],
    "nav-NS": ["method.name=nav", "method.form=NS", "method.alpha=0.48", "method.beta=126",
               "method.tau=0.1"],
}


@pytest.mark.parametrize("seed", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("name", list(TABLE1))
def test_seven_discs_reach_the_optimum(tmp_path, name, seed):
    """N = 7 unit discs from a standard Gaussian start, eps = 1e-6, l_inner = 10, eps_inner =
    1e-9: converges (exit 0) to the hexagon with its centre, W = 3, no overlap."""
    sets = ["n=7", "dim=2", "init.kind=gaussian", "init.sigma=1.0", f"seed={seed}",
            "method.l_inner=10", "method.eps_inner=1e-9", "stop.eps=1e-6", "stop.max_iter=20000"]
    proc, s, d = mpipack_run(1, tmp_path, None, sets + TABLE1[name], dump=True, timeout=RUN_TIMEOUT)
    assert proc.returncode == 0, describe(proc)
    assert s is not None and d is not None, describe(proc)
    # the paper's rule (4.3) fired; the packing is the optimum (checked directly below)
    assert s["stop_reason"] == "eps" and s["relative_change"] < 1e-6, s
    assert s["inner_iterations"] <= 10 * s["iterations"], s
    assert abs(s["W"] - 3.0) < 1e-3, s
    assert s["max_overlap"] < 1e-3, s
    # the same figures from the dumped positions
    x = d["x"]
    w = sum(float(((x[i + 1:] - x[i]) ** 2).sum()) for i in range(7)) / (2 * 7)
    assert w == pytest.approx(s["W"], rel=1e-10)
    r = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=2))
    np.fill_diagonal(r, np.inf)
    assert r.min() > 1.0 - 1e-3
    # the optimum: one disc in the middle touching six, each outer disc touching three
    contacts = (r < 1.0 + 1e-3).sum(axis=1)
    assert sorted(contacts.tolist()) == [3, 3, 3, 3, 3, 3, 6], contacts
