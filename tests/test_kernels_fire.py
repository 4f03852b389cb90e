"""The fire-al kernel against a numpy reference written from its formulas (kernels_fire's
docstring), the DAHA mode against the paper's kernel, and the fixed points."""

import math
import zlib

import numpy as np
import pytest

from mpipack.parallel import exactsum
from mpipack.kernels import daha as kernels, fire as kernels_fire
from mpipack.methods import fixed

from support import CENTRE, no_walls, random_cloud, random_lambda, ref_phi_grad, rows_complete


def ref_fire_al(form, x, x_prev, diam, lam_prev, xbar, a1, a2, a3, a4, beta, floor, clip,
                weighted, vmax, update):
    """(X^{n+1}, lambda, power, force2, max gain, max row) over all pairs k < l."""
    n, b = x.shape
    lam = lam_prev.copy()
    G = -a3 * (x - xbar)
    gain = np.zeros(n)
    row = np.zeros(n)
    for k in range(n):
        for l in range(k + 1, n):
            dkl = 0.5 * (diam[k] + diam[l])
            phi, g = ref_phi_grad(form, x[k], x[l], dkl)
            # the augmented Lagrangian's phi is per unit of the pair's size: phi / d_kl^p
            unit = (1.0 / dkl ** (2 if form == "S" else 1)) if clip else 1.0
            if update:
                wd = max(lam_prev[k, l], floor) if weighted else 1.0
                lam[k, l] = lam[l, k] = max(0.0, lam_prev[k, l] + beta * wd * phi * (unit if weighted else 1.0))
            w = max(lam[k, l], floor)
            m = a3 * lam[k, l] + a4 * w * phi * unit
            m = max(0.0, m) if clip else (m if lam[k, l] > 0 else 0.0)
            g2 = float(g @ g)
            r = math.sqrt(float((x[k] - x[l]) @ (x[k] - x[l])))
            hess = 2.0 if form == "S" else 1.0 / r
            if lam[k, l] > 0 or phi > 0:
                gain[k] += g2
                gain[l] += g2
            if m != 0:
                row[k] += a4 * w * g2 * unit + abs(m) * hess
                row[l] += a4 * w * g2 * unit + abs(m) * hess
                G[k] -= m * g
                G[l] += m * g
    V = x - x_prev
    D = (a1 - 1.0) * x + a2 * x_prev + G
    if vmax > 0:
        s = np.sqrt((D ** 2).sum(axis=1))
        big = s > vmax
        D[big] *= (vmax / s[big])[:, None]
    return x + D, lam, float((G * V).sum()), float((G * G).sum()), gain.max(), (a3 + 2 * row).max()


CASES = {
    # FIRE on the augmented Lagrangian: clip, floor, weighted continuous dual, speed cap
    "fire": dict(a1=1.3, a2=-0.3, a3=0.02, a4=0.08, beta=0.04, floor=0.7, clip=True, weighted=True, vmax=0.05),
    # the multiplier step: penalty off, dual gain rho = 4 max(lambda, floor)
    "alm": dict(a1=1.0, a2=0.0, a3=0.01, a4=0.0, beta=4.0, floor=0.7, clip=True, weighted=True, vmax=0.0),
    # the explosion: DAHA (2.10) with c = 2
    "daha": dict(a1=1.0, a2=0.0, a3=0.03, a4=0.05, beta=0.5, floor=0.0, clip=False, weighted=False, vmax=0.0),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_fire_kernel_matches_reference(dim, form, case):
    p = CASES[case]
    rng = np.random.default_rng(zlib.crc32(f"fire-{dim}-{form}-{case}".encode()))
    n = 30
    x, diam = random_cloud(rng, n, dim)
    x_prev = x + 0.05 * rng.normal(size=x.shape)
    lam_prev = random_lambda(rng, form, x, diam)
    gid = rng.permutation(n).astype(np.int64)
    xbar = x.mean(axis=0) + 0.01 * rng.normal(size=dim)
    x_ref, lam_ref, power, force2, gain, row = ref_fire_al(
        form, x, x_prev, diam, lam_prev, xbar, p["a1"], p["a2"], p["a3"], p["a4"], p["beta"],
        p["floor"], p["clip"], p["weighted"], p["vmax"], True)
    offsets, pair_j = rows_complete(n, n, gid)
    owner = np.repeat(np.arange(n), np.diff(offsets))
    pair_lambda = lam_prev[owner, pair_j].copy()
    x_new = np.full_like(x, np.nan)
    acc = exactsum.new_accumulator(dim + kernels_fire.N_ACC)
    maxima = np.zeros(kernels_fire.N_MAX)
    kern = kernels_fire.fire_al_step(form, dim)
    n_active = kern(x, x_prev, x_new, n, diam, offsets, pair_j, pair_lambda, *no_walls(n), xbar, CENTRE, p["a1"], p["a2"],
                    p["a3"], p["a4"], p["beta"], p["floor"], p["clip"], p["weighted"], p["vmax"],
                    True, acc, maxima)
    assert np.allclose(x_new, x_ref, rtol=1e-11, atol=1e-12), np.abs(x_new - x_ref).max()
    assert np.allclose(pair_lambda, lam_ref[owner, pair_j], rtol=1e-12, atol=1e-12)
    assert n_active == np.count_nonzero(lam_ref)
    if p["vmax"] > 0:
        assert np.sqrt(((x_new - x) ** 2).sum(axis=1)).max() <= p["vmax"] * (1 + 1e-12)
        assert np.sqrt(((x_ref - x) ** 2).sum(axis=1)).max() == pytest.approx(p["vmax"]), \
            "test set-up: the cap must bind somewhere"
    for k in range(dim):
        assert math.isclose(exactsum.value(acc, k), math.fsum(x_ref[:, k]), rel_tol=1e-11, abs_tol=1e-12)
    dx2 = ((x_ref - x) ** 2).sum(axis=1)
    assert math.isclose(exactsum.value(acc, dim + kernels_fire.ACC_DX2), math.fsum(dx2), rel_tol=1e-10)
    assert math.isclose(exactsum.value(acc, dim + kernels_fire.ACC_POWER), power, rel_tol=1e-9, abs_tol=1e-12)
    assert math.isclose(exactsum.value(acc, dim + kernels_fire.ACC_FORCE2), force2, rel_tol=1e-10)
    assert math.isclose(maxima[kernels_fire.MAX_STEP2], dx2.max(), rel_tol=1e-10)
    assert math.isclose(maxima[kernels_fire.MAX_GAIN], gain, rel_tol=1e-12)
    assert math.isclose(maxima[kernels_fire.MAX_ROW], row, rel_tol=1e-11)


@pytest.mark.parametrize("form", ["S", "NS"])
def test_daha_mode_is_the_paper_kernel(form):
    """No floor, no clip, no cap: the same X^{n+1} and lambda^n as kernels.multipliers_and_step."""
    rng = np.random.default_rng(7 + (form == "S"))
    n, dim = 40, 2
    x, diam = random_cloud(rng, n, dim)
    x_prev = x + 0.02 * rng.normal(size=x.shape)
    lam_prev = random_lambda(rng, form, x, diam)
    offsets, pair_j = rows_complete(n, n, np.arange(n, dtype=np.int64))
    owner = np.repeat(np.arange(n), np.diff(offsets))
    xbar = x.mean(axis=0)
    a1, a2, a3, a4 = fixed.paper_coefficients("daha", 0.2, 1.3, 0.4, 3.0)
    out = {}
    for name in ("paper", "fire"):
        lam = lam_prev[owner, pair_j].copy()
        x_new = np.empty_like(x)
        if name == "paper":
            acc, mx = exactsum.new_accumulator(dim + 2), np.zeros(kernels.N_MAX)
            kernels.multipliers_and_step(form, dim)(x, x_prev, x_new, n, diam, offsets, pair_j, lam,
                                                    *no_walls(n), xbar, CENTRE,
                                                    a1, a2, a3, a4, 1.3, True, acc, mx)
        else:
            acc, mx = exactsum.new_accumulator(dim + kernels_fire.N_ACC), np.zeros(kernels_fire.N_MAX)
            kernels_fire.fire_al_step(form, dim)(x, x_prev, x_new, n, diam, offsets, pair_j, lam,
                                                 *no_walls(n), xbar, CENTRE,
                                                 a1, a2, a3, a4, 1.3, 0.0, False, False, 0.0, True, acc, mx)
        out[name] = (x_new, lam)
    assert np.allclose(out["paper"][0], out["fire"][0], rtol=1e-13, atol=1e-13)
    assert np.array_equal(out["paper"][1], out["fire"][1])


def test_kkt_point_is_a_fixed_point():
    """Two touching spheres (S form) under W with their KKT multiplier: every mode leaves them
    where they are (Proposition 2.4 carries over: floor, clip and cap act on zero vectors)."""
    x = np.array([[-0.5, 0.0], [0.5, 0.0]])
    diam = np.ones(2)
    offsets = np.array([0, 1, 2], np.int64)
    pair_j = np.array([1, 0], np.int32)
    xbar = np.zeros(2)
    # grad W = X_i - Xbar = (-0.5, 0) for sphere 0; lambda grad phi = lambda (-2)(X_0 - X_1) = (2 lambda, 0)
    lam_star = 0.25
    for p in CASES.values():
        lam = np.full(2, lam_star)
        x_new = np.empty_like(x)
        acc, mx = exactsum.new_accumulator(2 + kernels_fire.N_ACC), np.zeros(kernels_fire.N_MAX)
        kernels_fire.fire_al_step("S", 2)(x, x, x_new, 2, diam, offsets, pair_j, lam, *no_walls(2), xbar, CENTRE,
                                          p["a1"], p["a2"],
                                          p["a3"], p["a4"], p["beta"], p["floor"], p["clip"], p["weighted"],
                                          p["vmax"], True, acc, mx)
        assert np.array_equal(x_new, x) and np.array_equal(lam, np.full(2, lam_star)), p


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_radial_equalisation_makes_a_uniform_ball(dim):
    """A Gaussian cloud spread by its own radial distribution: every centre keeps its direction
    and its rank in radius, and the radii become those of a uniform ball (F(r) = (r/R)^b), also
    when the histogram is summed from several ranks' parts."""
    from mpipack.engine import initial as init
    rng = np.random.default_rng(dim)
    n, radius = 4000, 30.0
    x = rng.normal(size=(n, dim)) * 0.7
    centre = x.mean(axis=0)
    r0 = np.sqrt(((x - centre) ** 2).sum(axis=1))
    r_max = r0.max()
    parts = [x[:1500], x[1500:]]  # two "ranks"
    counts = sum(init.radial_histogram(p, p.shape[0], centre, r_max) for p in parts)
    assert counts.dtype == np.int64 and counts.sum() == n
    spread = [p.copy() for p in parts]
    for p in spread:
        init.equalise_radially(p, p.shape[0], centre, r_max, counts, radius, dim)
    y = np.concatenate(spread)
    r1 = np.sqrt(((y - centre) ** 2).sum(axis=1))
    assert r1.max() <= radius * (1 + 1e-12)
    # directions kept, order of radii kept
    cos = ((x - centre) * (y - centre)).sum(axis=1) / (r0 * r1)
    assert np.all(cos > 1 - 1e-12)
    assert np.array_equal(np.argsort(r0, kind="stable"), np.argsort(r1, kind="stable"))
    # uniform in the ball: the fraction within q R is q^b
    for q in (0.3, 0.6, 0.9):
        assert abs((r1 <= q * radius).mean() - q ** dim) < 0.02, (q, (r1 <= q * radius).mean())
