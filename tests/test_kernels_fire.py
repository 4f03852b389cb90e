"""The fire-al kernel against a numpy reference written from its formulas (kernels_fire's
docstring), the DAHA mode against the paper's kernel, and the fixed points."""

import itertools
import math
import zlib

import numpy as np
import pytest

from mpipack.parallel import exactsum, neighbors
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


def half_list(dim, n_local, gid, offsets, pair_j, lam):
    """The pass's half list whatever the rows' length (these tests' rows are complete), from
    the entries' mirrors searched (``neighbors.find_mirrors``: what the rows' build finds)."""
    mirror = neighbors.find_mirrors(n_local, gid, offsets, pair_j)
    return kernels_fire.pair_work(dim, n_local, offsets, pair_j, lam, mirror, max_row=math.inf)


@pytest.mark.parametrize("walk", ["half list", "whole rows"])
@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_fire_kernel_matches_reference(dim, form, case, walk):
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
    pairs = half_list(dim, n, gid, offsets, pair_j, pair_lambda) if walk == "half list" else kernels_fire.WHOLE_ROWS
    assert (pairs[0].size > 0) == (walk == "half list")
    n_active = kern(x, x_prev, x_new, n, diam, offsets, pair_j, pair_lambda, pairs, *no_walls(n), xbar, CENTRE,
                    p["a1"], p["a2"],
                    p["a3"], p["a4"], p["beta"], p["floor"], p["clip"], p["weighted"], p["vmax"],
                    True, acc, maxima, False)
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
            pairs = half_list(dim, n, np.arange(n, dtype=np.int64), offsets, pair_j, lam)
            kernels_fire.fire_al_step(form, dim)(x, x_prev, x_new, n, diam, offsets, pair_j, lam, pairs,
                                                 *no_walls(n), xbar, CENTRE,
                                                 a1, a2, a3, a4, 1.3, 0.0, False, False, 0.0, True, acc, mx, False)
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
        pairs = half_list(2, 2, np.arange(2, dtype=np.int64), offsets, pair_j, lam)
        kernels_fire.fire_al_step("S", 2)(x, x, x_new, 2, diam, offsets, pair_j, lam, pairs, *no_walls(2), xbar,
                                          CENTRE,
                                          p["a1"], p["a2"],
                                          p["a3"], p["a4"], p["beta"], p["floor"], p["clip"], p["weighted"],
                                          p["vmax"], True, acc, mx, False)
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


def _every_entry_alone(dim, n_local, offsets, pair_j):
    """The ``pairs`` of a pass that computes every row entry on its own (no mirrors): the
    arithmetic of a pass over the whole of both rows of each pair."""
    n_pairs = int(offsets[n_local])
    owner = np.repeat(np.arange(n_local, dtype=np.int32), np.diff(offsets[:n_local + 1]))
    return (owner, np.arange(n_pairs, dtype=np.int64), pair_j[:n_pairs].copy(),
            np.full(n_pairs, -1, dtype=np.int64), np.empty((kernels_fire.n_terms(dim), n_pairs)))


@pytest.mark.parametrize("n, n_local", [(30, 30), (30, 17), (50, 50), (50, 33)])
def test_pair_halves_list_every_pair_once(n, n_local):
    """Every row entry is in the half list or is the mirror of one that is, never both; a
    mirror is the partner's entry of the same pair, both ways; ghost partners, and a pair whose
    two entries hold different lambdas, are listed from each side with no mirror. Rows of 29
    entries (a mirror found by a scan) and of 49 (by bisection on the gids)."""
    rng = np.random.default_rng(11 + n_local)
    gid = rng.permutation(n).astype(np.int64)
    offsets, pair_j = rows_complete(n_local, n, gid)
    owner = np.repeat(np.arange(n_local), np.diff(offsets))
    lam_full = rng.uniform(size=(n, n))
    lam_full = np.triu(lam_full, 1) + np.triu(lam_full, 1).T
    lam = lam_full[owner, pair_j].copy()
    odd = int(np.flatnonzero((pair_j < n_local) & (pair_j > owner))[3])  # one asymmetric pair
    lam[odd] *= 1.5
    half_i, half_e, half_j, half_f, _ = half_list(2, n_local, gid, offsets, pair_j, lam)
    assert np.array_equal(half_j, pair_j[half_e]) and np.all(np.diff(half_e) > 0)
    assert half_i.dtype == np.int32 and np.array_equal(half_i, owner[half_e])
    covered = np.zeros(offsets[n_local], dtype=int)
    covered[half_e] += 1
    covered[half_f[half_f >= 0]] += 1
    assert np.all(covered == 1)
    for e, f in zip(half_e, half_f):
        i, j = owner[e], pair_j[e]
        if f >= 0:
            assert owner[f] == j and pair_j[f] == i and j > i
        else:
            assert j >= n_local or e == odd or (i == pair_j[odd] and j == owner[odd])
    n_pairs_local = int(np.count_nonzero(pair_j < n_local))
    n_ghost = int(offsets[n_local]) - n_pairs_local
    assert half_e.size == n_pairs_local // 2 + 1 + n_ghost  # the odd pair from both sides


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [2, 3])
def test_each_pair_once_gives_the_bits_of_both_rows(dim, form, case):
    """The pass over the half list (each pair's terms once, written to both entries) leaves the
    same bits, in X^{n+1}, lambda, the exact sums and the maxima, as a pass that computes every
    entry of both rows, through the terms buffer or walking the whole rows (``WHOLE_ROWS``, a
    dense start's); with ghosts (the first 17 of 30 spheres local) and without."""
    p = CASES[case]
    rng = np.random.default_rng(zlib.crc32(f"half-{dim}-{form}-{case}".encode()))
    n = 30
    x, diam = random_cloud(rng, n, dim)
    diam = diam * rng.uniform(0.8, 1.2, size=n)
    x_prev = x + 0.05 * rng.normal(size=x.shape)
    lam_full = random_lambda(rng, form, x, diam)
    gid = rng.permutation(n).astype(np.int64)
    xbar = x.mean(axis=0)
    kern = kernels_fire.fire_al_step(form, dim)
    for n_local in (n, 17):
        offsets, pair_j = rows_complete(n_local, n, gid)
        owner = np.repeat(np.arange(n_local), np.diff(offsets))
        lam0 = lam_full[owner, pair_j].copy()
        out = []
        for pairs in (half_list(dim, n_local, gid, offsets, pair_j, lam0), _every_entry_alone(dim, n_local, offsets, pair_j),
                      kernels_fire.WHOLE_ROWS):
            lam = lam0.copy()
            x_new = np.full_like(x, np.nan)
            acc = exactsum.new_accumulator(dim + kernels_fire.N_ACC)
            maxima = np.zeros(kernels_fire.N_MAX)
            active = kern(x, x_prev, x_new, n_local, diam, offsets, pair_j, lam, pairs, *no_walls(n_local), xbar,
                          CENTRE, p["a1"], p["a2"], p["a3"], p["a4"], p["beta"], p["floor"], p["clip"],
                          p["weighted"], p["vmax"], True, acc, maxima, False)
            out.append((x_new[:n_local], lam, acc, maxima, active))
        assert out[0][1].size > 0 and np.count_nonzero(out[0][1]) > 0
        for other in out[1:]:
            for a, b in zip(out[0], other):
                assert np.array_equal(a, b), (n_local, a, b)


@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_gradient_pass_moves_as_the_full_pass(dim, form):
    """L-BFGS's gradient pass (a1 = 1, a2 = 0, no dual step: the kernel with gradient_pass)
    leaves the bits of the full pass with the same coefficients in X^{n+1} = X^n - grad L_rho,
    lambda, |X^n|^2, the largest move and overlap and the active count, over the half list and
    over whole rows, without reading X^{n-1} (NaN here); it sums nothing else."""
    rng = np.random.default_rng(zlib.crc32(f"grad-{dim}-{form}".encode()))
    n = 30
    x, diam = random_cloud(rng, n, dim)
    lam_full = random_lambda(rng, form, x, diam)
    gid = rng.permutation(n).astype(np.int64)
    xbar = x.mean(axis=0)
    kern = kernels_fire.fire_al_step(form, dim)
    # a1 .. vmax: the stiff phase's gradient; and without the clip and weighted dual (the
    # kernel's general branch)
    for coeffs, n_local in itertools.product(((1.0, 0.0, 1.0, 0.3, 0.0, 0.7, True, True, 0.0),
                                              (1.0, 0.0, 1.0, 0.3, 0.0, 0.0, False, False, 0.0)), (n, 17)):
        offsets, pair_j = rows_complete(n_local, n, gid)
        owner = np.repeat(np.arange(n_local), np.diff(offsets))
        lam0 = lam_full[owner, pair_j].copy()
        for pairs in (half_list(dim, n_local, gid, offsets, pair_j, lam0), kernels_fire.WHOLE_ROWS):
            out = []
            for gradient_pass, x_prev in ((False, x + 0.05 * rng.normal(size=x.shape)), (True, np.full_like(x, np.nan))):
                lam = lam0.copy()
                x_new = np.full_like(x, np.nan)
                acc = exactsum.new_accumulator(dim + kernels_fire.N_ACC)
                maxima = np.zeros(kernels_fire.N_MAX)
                active = kern(x, x_prev, x_new, n_local, diam, offsets, pair_j, lam, pairs, *no_walls(n_local), xbar,
                              CENTRE, *coeffs, True, acc, maxima, gradient_pass)
                out.append((x_new[:n_local], lam, acc, maxima, active))
            full, grad = out
            assert np.isfinite(grad[0]).all() and not np.array_equal(grad[0], x[:n_local])
            assert np.array_equal(full[0], grad[0]) and np.array_equal(full[1], grad[1]) and full[4] == grad[4]
            xx2 = dim + kernels_fire.ACC_XX2
            assert np.array_equal(full[2][xx2], grad[2][xx2])
            assert not grad[2][np.arange(dim + kernels_fire.N_ACC) != xx2].any()
            for m in (kernels_fire.MAX_STEP2, kernels_fire.MAX_OVERLAP):
                assert full[3][m] == grad[3][m]


def test_dense_rows_get_no_half_list():
    """Rows of more than HALF_LIST_MAX_ROW entries a sphere (a dense start's first pass) are
    walked whole: no half list, whose memory would outgrow the rows' own guard."""
    n = kernels_fire.HALF_LIST_MAX_ROW + 2
    gid = np.arange(n, dtype=np.int64)
    offsets, pair_j = rows_complete(n, n, gid)  # n - 1 > HALF_LIST_MAX_ROW entries a sphere
    lam = np.zeros(offsets[n])
    mirror = neighbors.find_mirrors(n, gid, offsets, pair_j)
    assert kernels_fire.pair_work(2, n, offsets, pair_j, lam, mirror) is kernels_fire.WHOLE_ROWS
    offsets, pair_j = rows_complete(n - 4, n - 4, gid)
    mirror = neighbors.find_mirrors(n - 4, gid, offsets, pair_j)
    work = kernels_fire.pair_work(2, n - 4, offsets, pair_j, lam[:offsets[n - 4]], mirror)
    m = n - 4  # each pair once: m (m - 1) / 2 listed entries
    assert work[0].shape == (m * (m - 1) // 2,) and work[4].shape == (4, offsets[m])
    # rows whose build found no mirrors (a gid twice) are walked whole too
    assert kernels_fire.pair_work(2, n - 4, offsets, pair_j, lam[:offsets[n - 4]], None) is kernels_fire.WHOLE_ROWS
