"""Serial kernels against plain numpy references written from the paper's formulas.

Reference: Degond, Ferreira, Motsch 2017, (2.8) (AHA), (2.10) (DAHA) and its gamma form of
section 4.3, with W = 1/(2N) sum_{i<j} |X_i - X_j|^2 (3.1) and pairwise diameters
d_kl = (d_k + d_l)/2. The references loop over the pairs k < l of the whole system and add
each pair's gradient to both of its spheres (the kernel instead walks one row per sphere).
"""

import math
import zlib

import numpy as np
import pytest

from support import CENTRE, no_walls, random_cloud, random_lambda, ref_phi_grad, rows_complete

from mpipack.jit import njit
from mpipack.parallel import exactsum, neighbors
from mpipack.kernels import daha as kernels
from mpipack.kernels import fire as kernels_fire
from mpipack.methods import fixed

# ---------------------------------------------------------------------------------------------
# reference implementation
# ---------------------------------------------------------------------------------------------


def ref_step(method, form, x, x_prev, diam, lam_prev, alpha, beta, gamma, c, update_lambda,
             xbar=None):
    """One iteration n -> n+1 of AHA (2.8) or DAHA (2.10, gamma form of section 4.3).

    x = X^n, x_prev = X^{n-1} (N, b); lam_prev: symmetric (N, N) matrix of lambda^{n-1}
    (lambda^n itself when update_lambda is False). Returns (X^{n+1}, lambda^n).
    """
    n, b = x.shape
    if xbar is None:
        xbar = x.mean(axis=0)
    lam = lam_prev.copy()
    pairs = [(k, l) for k in range(n) for l in range(k + 1, n)]
    phi = {}
    grad = {}
    for k, l in pairs:
        phi[k, l], grad[k, l] = ref_phi_grad(form, x[k], x[l], 0.5 * (diam[k] + diam[l]))
    if update_lambda:  # (2.10b) / (2.8b): lambda^n = max(0, lambda^{n-1} + beta phi(X^n))
        for k, l in pairs:
            lam[k, l] = lam[l, k] = max(0.0, lam_prev[k, l] + beta * phi[k, l])
    grad_w = x - xbar  # grad_{X_i} W(X) for W of (3.1)
    s_lam = np.zeros_like(x)  # sum_kl lambda_kl grad_{X_i} phi_kl
    s_phi_lam = np.zeros_like(x)  # sum_kl phi_kl lambda_kl grad_{X_i} phi_kl
    for k, l in pairs:
        g = grad[k, l]
        s_lam[k] += lam[k, l] * g
        s_lam[l] -= lam[k, l] * g
        s_phi_lam[k] += phi[k, l] * lam[k, l] * g
        s_phi_lam[l] -= phi[k, l] * lam[k, l] * g
    if method == "aha":
        x_new = x - alpha * (grad_w + s_lam)
    else:
        h = 1.0 + c / 2.0
        x_new = (2.0 * x - (1.0 - c / 2.0) * x_prev) / h \
            - alpha ** 2 / h * (grad_w + s_lam) - gamma ** 2 / h * s_phi_lam
    return x_new, lam


def run_kernel(form, x, x_prev, diam, offsets, pair_j, pair_lambda, xbar, coeffs, beta,
               update_lambda, n_local):
    kern = kernels.multipliers_and_step_s if form == "S" else kernels.multipliers_and_step_ns
    b = x.shape[1]
    x_new = np.full_like(x, np.nan)
    acc = exactsum.new_accumulator(b + 2)
    maxima = np.zeros(kernels.N_MAX)
    a1, a2, a3, a4 = coeffs
    n_active = kern(x, x_prev, x_new, n_local, diam, offsets, pair_j, pair_lambda, *no_walls(n_local), xbar, CENTRE,
                    a1, a2, a3, a4, beta, update_lambda, acc, maxima)
    return x_new, acc, maxima, n_active


PARAMS = {
    # DAHA, gamma form (gamma != sqrt(alpha beta)), c != 2 so that X^{n-1} matters
    "daha-gamma": dict(method="daha", alpha=0.3, beta=1.4, gamma=0.45, c=1.5),
    # DAHA with c > 2 (negative weight on X^{n-1} flips sign)
    "daha-c3": dict(method="daha", alpha=0.2, beta=3.0, gamma=math.sqrt(0.6), c=3.0),
    # AHA (2.8): one-step, no damping, no phi*lambda term
    "aha": dict(method="aha", alpha=0.05, beta=0.7, gamma=0.0, c=2.0),
}


@pytest.mark.parametrize("update_lambda", [True, False], ids=["update", "first"])
@pytest.mark.parametrize("pname", list(PARAMS))
@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_kernel_matches_reference(dim, form, pname, update_lambda):
    p = PARAMS[pname]
    seed = zlib.crc32(f"{dim}-{form}-{pname}-{update_lambda}".encode())
    rng = np.random.default_rng(seed)
    n = 30
    x, diam = random_cloud(rng, n, dim)
    x_prev = x + 0.05 * rng.normal(size=x.shape)
    lam_prev = random_lambda(rng, form, x, diam)
    assert np.count_nonzero(lam_prev) > 10, "test set-up: want many active pairs"
    # global ids are a permutation: rows are sorted by gid, not by index
    gid = rng.permutation(n).astype(np.int64)
    xbar = x.mean(axis=0) + 0.01 * rng.normal(size=dim)  # the kernel takes Xbar as given

    x_ref, lam_ref = ref_step(p["method"], form, x, x_prev, diam, lam_prev, p["alpha"], p["beta"],
                              p["gamma"], p["c"], update_lambda, xbar=xbar)

    coeffs = fixed.paper_coefficients(p["method"], p["alpha"], p["beta"], p["gamma"], p["c"])
    offsets, pair_j = rows_complete(n, n, gid)
    owner = np.repeat(np.arange(n), np.diff(offsets))
    pair_lambda = lam_prev[owner, pair_j].copy()
    x_new, acc, maxima, n_active = run_kernel(form, x, x_prev, diam, offsets, pair_j, pair_lambda,
                                              xbar, coeffs, p["beta"], update_lambda, n)

    assert np.allclose(x_new, x_ref, rtol=1e-12, atol=1e-12), np.abs(x_new - x_ref).max()
    # (2.10b) lambda^n in every row entry, and both ends of a pair hold the same bits
    assert np.allclose(pair_lambda, lam_ref[owner, pair_j], rtol=1e-12, atol=1e-12)
    mirror = {(owner[e], pair_j[e]): pair_lambda[e] for e in range(pair_j.shape[0])}
    assert all(mirror[i, j] == mirror[j, i] for (i, j) in mirror)
    if not update_lambda:
        assert np.array_equal(pair_lambda, lam_prev[owner, pair_j])
    # active row entries: each lambda^n > 0 pair counted from both ends
    assert n_active == np.count_nonzero(lam_ref)
    # exact per-step sums: sum X^{n+1}, sum |X^{n+1} - X^n|^2, sum |X^n|^2
    for k in range(dim):
        assert math.isclose(exactsum.value(acc, k), math.fsum(x_ref[:, k]), rel_tol=1e-12,
                            abs_tol=1e-12)
    assert math.isclose(exactsum.value(acc, dim), math.fsum(((x_ref - x) ** 2).sum(axis=1)),
                        rel_tol=1e-10, abs_tol=1e-12)
    assert math.isclose(exactsum.value(acc, dim + 1), math.fsum((x ** 2).ravel()), rel_tol=1e-14)
    # maxima: displacement since the build, largest relative overlap at X^n
    step2 = ((x_ref - x) ** 2).sum(axis=1).max()
    assert math.isclose(maxima[kernels.MAX_STEP2], step2, rel_tol=1e-10)
    r = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=2))
    dkl = 0.5 * (diam[:, None] + diam[None, :])
    ov = (dkl - r) / dkl
    np.fill_diagonal(ov, 0.0)
    assert math.isclose(maxima[kernels.MAX_OVERLAP], max(ov.max(), 0.0), rel_tol=1e-12)


@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_kernel_with_ghosts_and_verlet_rows(dim, form):
    """Rows from build_rows (only partners within d_ij + skin), locals first then ghosts: the
    local part of X^{n+1} is that of the full system (lambda^{n-1} lives on overlapping pairs
    only, so the pairs left out of the rows keep lambda = 0)."""
    p = PARAMS["daha-gamma"]
    rng = np.random.default_rng(100 + dim + (form == "S"))
    n, n_local = 40, 25
    x, diam = random_cloud(rng, n, dim)
    x_prev = x - 0.03 * rng.normal(size=x.shape)
    lam_prev = random_lambda(rng, form, x, diam, frac=1.0)
    gid = rng.permutation(n).astype(np.int64)
    xbar = x.mean(axis=0)
    x_ref, lam_ref = ref_step("daha", form, x, x_prev, diam, lam_prev, p["alpha"], p["beta"],
                              p["gamma"], p["c"], True)
    empty = (np.zeros(n_local + 1, np.int64), np.empty(0, np.int64), np.empty(0))
    offsets, pair_j, pair_lambda, missing, _ = neighbors.build_rows(x, n_local, n, gid, diam, 0.3,
                                                                 *empty)
    assert missing == 0
    owner = np.repeat(np.arange(n_local), np.diff(offsets))
    assert pair_j.shape[0] < n_local * (n - 1), "test set-up: rows should not be complete"
    pair_lambda[:] = lam_prev[owner, pair_j]
    assert np.count_nonzero(pair_lambda) == np.count_nonzero(lam_prev[:n_local]), \
        "every overlapping pair of a local particle must be in its row"
    coeffs = fixed.paper_coefficients("daha", p["alpha"], p["beta"], p["gamma"], p["c"])
    x_new, _, _, _ = run_kernel(form, x, x_prev, diam, offsets, pair_j, pair_lambda, xbar,
                                coeffs, p["beta"], True, n_local)
    assert np.allclose(x_new[:n_local], x_ref[:n_local], rtol=1e-12, atol=1e-12)
    assert np.all(np.isnan(x_new[n_local:])), "ghost rows of x_new must not be written"
    assert np.allclose(pair_lambda, lam_ref[owner, pair_j], rtol=1e-12, atol=1e-12)


def test_coefficients_follow_the_paper():
    alpha, beta, gamma, c = 0.3, 1.4, 0.5, 1.2
    h = 1 + c / 2
    a = fixed.paper_coefficients("daha", alpha, beta, gamma, c)
    assert np.allclose(a, (2 / h, -(1 - c / 2) / h, alpha ** 2 / h, gamma ** 2 / h), rtol=1e-15)
    # c = 2: the one-step method, X^{n-1} drops out
    assert fixed.paper_coefficients("daha", alpha, beta, gamma, 2.0)[1] == 0.0
    assert fixed.paper_coefficients("aha", alpha, beta, gamma, c) == (1.0, 0.0, alpha, 0.0)
    with pytest.raises(ValueError):
        fixed.paper_coefficients("nap", alpha, beta, gamma, c)


def test_two_step_trajectory_matches_reference():
    """A few chained DAHA iterations (lambda fresh on the first, updated afterwards)."""
    p = PARAMS["daha-gamma"]
    rng = np.random.default_rng(7)
    n, dim, form = 20, 2, "S"
    x, diam = random_cloud(rng, n, dim)
    x_prev = x.copy()
    gid = np.arange(n, dtype=np.int64)
    offsets, pair_j = rows_complete(n, n, gid)
    owner = np.repeat(np.arange(n), np.diff(offsets))
    pair_lambda = np.zeros(pair_j.shape[0])
    coeffs = fixed.paper_coefficients("daha", p["alpha"], p["beta"], p["gamma"], p["c"])
    rx, rxp, rlam = x.copy(), x_prev.copy(), np.zeros((n, n))
    kx, kxp = x.copy(), x_prev.copy()
    for it in range(5):
        rnew, rlam = ref_step("daha", form, rx, rxp, diam, rlam, p["alpha"], p["beta"],
                              p["gamma"], p["c"], it > 0)
        knew, _, _, _ = run_kernel(form, kx, kxp, diam, offsets, pair_j, pair_lambda,
                                   kx.mean(axis=0), coeffs, p["beta"], it > 0, n)
        rxp, rx = rx, rnew
        kxp, kx = kx, knew
        assert np.allclose(kx, rx, rtol=1e-12, atol=1e-12), it
        assert np.allclose(pair_lambda, rlam[owner, pair_j], rtol=1e-12, atol=1e-12), it
    assert np.count_nonzero(pair_lambda) > 0


# ---------------------------------------------------------------------------------------------
# exact sums
# ---------------------------------------------------------------------------------------------


def mixed_values(rng, n):
    mag = 10.0 ** rng.uniform(-12, 12, size=n)
    return mag * rng.choice([-1.0, 1.0], size=n)


def test_exact_sum_is_order_independent_and_accurate():
    rng = np.random.default_rng(2017)
    v = mixed_values(rng, 100_000)
    ref = exactsum.exact_sum(v)
    # plain float sums of these permutations differ: the order matters without exactsum
    naive = {float(np.sum(rng.permutation(v))) for _ in range(6)}
    assert len(naive) > 1
    for _ in range(6):
        s = exactsum.exact_sum(rng.permutation(v))
        assert s == ref and np.float64(s).tobytes() == np.float64(ref).tobytes()
    assert exactsum.exact_sum(v[::-1]) == ref
    assert math.isclose(ref, math.fsum(v), rel_tol=1e-15, abs_tol=1e-12)


def test_exact_sum_small_values_and_cancellation():
    rng = np.random.default_rng(5)
    # tiny values only: resolution 2**-78 is far below them
    v = rng.uniform(-1e-9, 1e-9, size=50_000)
    s = exactsum.exact_sum(v)
    assert math.isclose(s, math.fsum(v), rel_tol=1e-12, abs_tol=1e-20)
    # exact cancellation of large terms leaves the small ones
    big = rng.uniform(-1e12, 1e12, size=1000)
    small = rng.uniform(0, 1e-3, size=1000)
    w = np.concatenate([big, small, -big])
    for _ in range(3):
        t = exactsum.exact_sum(rng.permutation(w))
        assert math.isclose(t, math.fsum(small), rel_tol=1e-15)


def test_exact_sum_partial_accumulators_combine_exactly():
    """What the MPI reduction does: integer-adding accumulators of arbitrary chunks gives the
    same bits as the whole array, whatever the split."""
    rng = np.random.default_rng(11)
    v = mixed_values(rng, 30_000)
    whole = exactsum.exact_sum(v)
    for parts in (2, 3, 7):
        perm = rng.permutation(v.shape[0])
        cuts = np.sort(rng.choice(np.arange(1, v.shape[0]), size=parts - 1, replace=False))
        total = exactsum.new_accumulator(1)
        for chunk in np.split(v[perm], cuts):
            acc = exactsum.new_accumulator(1)
            exactsum.accumulate(np.ascontiguousarray(chunk), acc, 0)
            total += acc
        assert exactsum.value(total, 0) == whole


def test_exact_sum_columns_match_per_value_adds():
    """``columns`` (values put item by item, cut and summed a block of items at a time down
    each quantity's column, the sums reassociated) leaves the same accumulator, bit for bit, as
    per-value ``add`` calls: over more than FLUSH_EVERY items and a last partial block, with
    values of every magnitude, zeros, -0.0, out-of-range values and NaN in some quantities
    only, and quantities put for some items only (zeros for the others)."""
    from numba import njit

    @njit
    def by_value(vals, acc):
        fbuf = exactsum.staging(acc)
        for i in range(vals.shape[0]):
            for q in range(vals.shape[1]):
                if q != 9 or vals[i, 0] > 0.0:
                    exactsum.add(fbuf, acc, q, vals[i, q])
        exactsum.flush(fbuf, acc)

    @njit
    def by_columns(vals, acc):
        cols = exactsum.columns(acc)
        for i in range(vals.shape[0]):
            for q in range(vals.shape[1]):
                if q != 9 or vals[i, 0] > 0.0:
                    exactsum.put(cols, q, i, vals[i, q])
            if exactsum.block_ends(i):
                exactsum.add_block(cols, acc)
        exactsum.flush_columns(cols, acc, vals.shape[0])

    rng = np.random.default_rng(23)
    n, k = 5 * exactsum.FLUSH_EVERY + 17, 15
    vals = mixed_values(rng, n * k).reshape(n, k)
    vals[:, 4] = 0.0
    vals[::7, 5] = -0.0
    vals[100, 6] = np.nan
    vals[200, 7] = 2.0 * exactsum.RANGE
    vals[300, 8] = -np.inf
    vals[:, 10] = 2.0 ** -60 * rng.integers(1, 1000, size=n)  # tiny, exact in the last bin
    # near the range, one sign: more than 2**13 of these overflow a float partial sum's 53 bits
    # unless it is moved to the integers every FLUSH_EVERY values
    vals[:, 11] = exactsum.RANGE * rng.uniform(0.98, 0.99, size=n)
    # columns cut into their lower bins only (all values below the bound of bin 1, or of bin
    # 0), with values at the bounds and just below them in some blocks
    vals[:, 12] = rng.uniform(-1.0, 1.0, size=n) * 10.0 ** rng.uniform(-20, 0.6, size=n)
    vals[:, 13] = rng.uniform(-1.0, 1.0, size=n) * 10.0 ** rng.uniform(-20, 12.9, size=n)
    for col, bound in ((12, exactsum._BELOW_BIN1), (13, exactsum._BELOW_BIN0)):
        for t, v in enumerate((bound, np.nextafter(bound, 0.0), -np.nextafter(bound, 0.0),
                               2.0 * bound, -bound)):
            vals[(t + 1) * 3 * exactsum.COLUMN_BLOCK + 5, col] = v
    for m in (1, exactsum.COLUMN_BLOCK - 1, exactsum.COLUMN_BLOCK, exactsum.COLUMN_BLOCK + 1, n):
        a, b = exactsum.new_accumulator(k), exactsum.new_accumulator(k)
        by_value(vals[:m], a)
        by_columns(vals[:m], b)
        assert np.array_equal(a, b), m
    got = exactsum.values_all(b)
    assert np.isnan(got[6:9]).all() and got[4] == 0.0
    for q in (0, 3, 10, 11, 12, 13, 14):
        assert got[q] == exactsum.exact_sum(vals[:, q])
    assert got[9] == exactsum.exact_sum(vals[vals[:, 0] > 0.0, 9])
    # accumulators of any split of the rows add up to the whole, as an allreduce does
    c = exactsum.new_accumulator(k)
    for chunk in np.array_split(vals, 5):
        part = exactsum.new_accumulator(k)
        by_columns(np.ascontiguousarray(chunk), part)
        c += part
    assert np.array_equal(exactsum.values_all(c), got, equal_nan=True)


def test_exact_sum_out_of_range_is_nan():
    v = np.array([1.0, 2.0, 2.0 * exactsum.RANGE, 3.0])
    assert math.isnan(exactsum.exact_sum(v))
    # squares of positions far from the origin (|X| ~ 5e6 -> 2.5e13) are in range
    assert exactsum.exact_sum(np.array([2.5e13, 1.0, -2.5e13])) == 1.0
    assert math.isnan(exactsum.exact_sum(np.array([1.0, np.nan])))
    assert math.isnan(exactsum.exact_sum(np.array([np.inf])))
    assert exactsum.exact_sum(np.zeros(0)) == 0.0


# ---------------------------------------------------------------------------------------------
# neighbour rows
# ---------------------------------------------------------------------------------------------


def brute_rows(x, n_local, gid, diam, skin):
    n = x.shape[0]
    rows = []
    for i in range(n_local):
        r = []
        for j in range(n):
            if j == i:
                continue
            rc = 0.5 * (diam[i] + diam[j]) + skin
            if float(np.sum((x[i] - x[j]) ** 2)) < rc * rc:
                r.append(int(gid[j]))
        rows.append(sorted(r))
    return rows


def rows_as_gids(offsets, pair_j, gid):
    return [[int(g) for g in gid[pair_j[offsets[i]:offsets[i + 1]]]]
            for i in range(offsets.shape[0] - 1)]


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_build_rows_matches_brute_force(dim):
    rng = np.random.default_rng(40 + dim)
    n, n_local = 80, 50
    # a spread-out cloud with a dense core, polydisperse
    x = np.concatenate([rng.normal(size=(n // 2, dim)),
                        rng.uniform(-6, 6, size=(n - n // 2, dim))])
    x = x[rng.permutation(n)]
    diam = rng.uniform(0.7, 1.4, size=n)
    gid = (rng.permutation(n) * 3 + 5).astype(np.int64)  # not 0..n-1
    for skin in (0.0 + 1e-9, 0.3, 1.1):
        empty = (np.zeros(n_local + 1, np.int64), np.empty(0, np.int64), np.empty(0))
        off, pj, pl, missing, _ = neighbors.build_rows(x, n_local, n, gid, diam, skin, *empty)
        assert missing == 0
        assert off.shape == (n_local + 1,) and off[0] == 0
        assert pj.dtype == np.int32
        got = rows_as_gids(off, pj, gid)
        want = brute_rows(x, n_local, gid, diam, skin)
        assert got == want, f"skin {skin}"
        assert np.all(pl == 0.0)
        assert sum(len(r) for r in want) > 0


@njit
def _rank_sort(g, j, n, g_work, j_work):
    return neighbors._rank_sort(g, j, n, g_work, j_work)


def test_rank_sort_sorts_or_refuses_equal_keys():
    """A row's sort by ranks: keys ascending and partners alike for distinct keys (rows of 0 to
    48 entries), in place, nothing past n touched; with two equal keys it says so (False) and
    leaves the row as it was, and the build then sorts by insertion."""
    rng = np.random.default_rng(5)
    for n in (0, 1, 2, 7, 14, 48):
        g = np.concatenate([rng.permutation(10 * n + 1)[:n], [-3, -3]]).astype(np.int64)
        j = rng.integers(0, 1000, size=n + 2).astype(np.int64)
        g0, j0 = g.copy(), j.copy()
        assert _rank_sort(g, j, n, np.empty(n + 2, np.int64), np.empty(n + 2, np.int64))
        o = np.argsort(g0[:n])
        assert np.array_equal(g[:n], g0[o]) and np.array_equal(j[:n], j0[o])
        assert np.array_equal(g[n:], g0[n:]) and np.array_equal(j[n:], j0[n:])
    g = np.array([9, 4, 9, 1], np.int64)
    j = np.arange(4, dtype=np.int64)
    assert not _rank_sort(g, j, 4, np.empty(4, np.int64), np.empty(4, np.int64))
    assert g.tolist() == [9, 4, 9, 1] and j.tolist() == [0, 1, 2, 3]


@njit
def _build_rows_sorted(b, x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries):
    return neighbors._build_rows_sorted(b, x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries)


def _moved_with_history(rng, x, n_local, gid, diam, skin, shift):
    """Rows at x, lambda > 0 on about half the entries (a pair's two entries mostly alike,
    some not), the history they give, and x moved by ``shift``: some history partners far."""
    n = x.shape[0]
    empty = (np.zeros(n_local + 1, np.int64), np.empty(0, np.int64), np.empty(0))
    off, pj, _, _, _ = neighbors.build_rows(x, n_local, n, gid, diam, skin, *empty)
    lam = np.where(rng.random(pj.shape[0]) < 0.5, rng.random(pj.shape[0]) + 0.01, 0.0)
    row = np.repeat(np.arange(n_local), np.diff(off))
    first = {}
    for e in range(pj.shape[0]):
        key = tuple(sorted((int(gid[row[e]]), int(gid[pj[e]]))))
        if key in first and rng.random() < 0.8:
            lam[e] = lam[first[key]]
        first.setdefault(key, e)
    hist = neighbors.history(n_local, gid, off, pj, lam)
    return x + rng.normal(0.0, shift, x.shape), hist


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_build_rows_finds_each_pair_once_with_the_same_rows(dim):
    """The build that finds each pair once gives the rows, bit for bit, of the build that makes
    one row at a time, and each entry's mirror as ``find_mirrors`` searches it (history
    partners beyond reach in both rows included); where it leaves the build to the other (a
    dense start's rows, a gid twice among the particles) the rows are the other's, with no
    mirror."""
    rng = np.random.default_rng(60 + dim)
    cases = once = 0
    for n, n_local, density, poly in ((400, 400, 1.0, False), (400, 250, 1.0, True),
                                      (300, 200, 3.0, False), (60, 30, 0.3, True)):
        side = (n / density) ** (1.0 / dim)
        x = rng.uniform(0.0, side, size=(n, dim))
        diam = rng.lognormal(0.0, 0.3, n) if poly else np.ones(n)
        gid = (rng.permutation(3 * n)[:n] + 7).astype(np.int64)
        for skin in (0.05, 0.3, 1.0):
            x2, hist = _moved_with_history(rng, x, n_local, gid, diam, skin, 0.7 * skin + 0.05)
            off, pj, pl, missing, mirror = neighbors.build_rows(x2, n_local, n, gid, diam, skin, *hist)
            want = _build_rows_sorted(dim, x2, n_local, n, gid, diam, skin, *hist, np.int64(2 ** 62))
            assert np.array_equal(off, want[0]) and np.array_equal(pj, want[1]) and pj.dtype == np.int32
            assert pl.tobytes() == want[2].tobytes() and missing == want[3] == 0
            if mirror is None:  # (rows too long for it: more than PAIRS_ONCE_MAX pairs a sphere)
                assert off[-1] > neighbors.PAIRS_ONCE_MAX * n_local
                continue
            once += 1
            assert np.array_equal(mirror, neighbors.find_mirrors(n_local, gid, off, pj))
            # the half list from the build's mirrors is the one from searched mirrors
            found = kernels_fire.pair_work(dim, n_local, off, pj, pl, mirror, max_row=np.inf)
            searched = kernels_fire.pair_work(dim, n_local, off, pj, pl, neighbors.find_mirrors(
                n_local, gid, off, pj), max_row=np.inf)
            assert all(np.array_equal(a, b) for a, b in zip(found[:4], searched[:4]))
            # mirrors of far history partners: beyond d_ij + skin in both rows
            row = np.repeat(np.arange(n_local), np.diff(off))
            far = np.linalg.norm(x2[row] - x2[pj], axis=1) >= 0.5 * (diam[row] + diam[pj]) + skin
            cases += int(np.sum(far & (mirror >= 0)))
    assert cases > 0, "test set-up: some far history pair in both rows"
    assert once >= 9, "test set-up: most cases are the build's usual ones"
    # a dense start: rows of hundreds of entries, the row-at-a-time build, no mirrors
    n = 1500
    x = rng.normal(0.0, 1.0, size=(n, dim))
    gid = np.arange(n, dtype=np.int64)
    empty = (np.zeros(n + 1, np.int64), np.empty(0, np.int64), np.empty(0))
    off, pj, pl, missing, mirror = neighbors.build_rows(x, n, n, gid, np.ones(n), 0.05, *empty)
    want = _build_rows_sorted(dim, x, n, n, gid, np.ones(n), 0.05, *empty, np.int64(2 ** 62))
    assert off[-1] > 2 * neighbors.PAIRS_ONCE_MAX * n and mirror is None
    assert np.array_equal(off, want[0]) and np.array_equal(pj, want[1])
    # a gid twice (a ghost copy of a local): the other build, no mirrors
    n, n_local = 200, 150
    x = rng.uniform(0.0, n ** (1.0 / dim), size=(n, dim))
    gid = np.arange(n, dtype=np.int64)
    gid[160], x[160] = 3, x[3] + 0.3
    empty = (np.zeros(n_local + 1, np.int64), np.empty(0, np.int64), np.empty(0))
    off, pj, pl, missing, mirror = neighbors.build_rows(x, n_local, n, gid, np.ones(n), 0.3, *empty)
    want = _build_rows_sorted(dim, x, n_local, n, gid, np.ones(n), 0.3, *empty, np.int64(2 ** 62))
    assert mirror is None and np.array_equal(off, want[0]) and np.array_equal(pj, want[1])


def test_history_keeps_the_partners_with_lambda_above_zero():
    """A row's history: its partners' gids with lambda > 0, in row order (gid order), none with
    lambda 0, negative or NaN; offsets per local sphere (rows with none, a last row that is
    all history)."""
    rng = np.random.default_rng(8)
    n_local, n_total = 6, 9
    gid = (rng.permutation(n_total) * 5 + 2).astype(np.int64)
    lengths = [3, 0, 4, 2, 1, 3]
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    pair_j = np.concatenate([rng.choice([k for k in range(n_total) if k != i], size=m, replace=False)
                             for i, m in enumerate(lengths)]).astype(np.int32)
    lam = np.array([0.5, 0.0, 2.0, 0.0, -1.0, np.nan, 1e-300, 0.0, 3.0, 0.0, 0.25, 0.7, 0.1])
    h_off, h_gid, h_lam = neighbors.history(n_local, gid, offsets, pair_j, lam)
    want_off, want_gid, want_lam = [0], [], []
    for i in range(n_local):
        for e in range(offsets[i], offsets[i + 1]):
            if lam[e] > 0:
                want_gid.append(int(gid[pair_j[e]]))
                want_lam.append(lam[e])
        want_off.append(len(want_gid))
    assert h_off.tolist() == want_off == [0, 2, 2, 3, 4, 4, 7]
    assert h_gid.tolist() == want_gid and h_lam.tolist() == want_lam
    assert h_gid.dtype == np.int64 and h_lam.dtype == np.float64


def test_build_rows_keeps_history():
    rng = np.random.default_rng(3)
    dim, n, n_local = 2, 40, 30
    x = rng.uniform(-5, 5, size=(n, dim))
    diam = np.full(n, 1.0)
    gid = np.arange(100, 100 + n, dtype=np.int64)[rng.permutation(n)]
    skin = 0.3
    want = brute_rows(x, n_local, gid, diam, skin)
    # history of particle 0: a far partner (present), a near partner (present, merged), and a
    # gid that is nowhere (missing)
    dist = np.sqrt(((x - x[0]) ** 2).sum(axis=1))
    far = int(np.argmax(dist))
    assert dist[far] > 1.0 + skin
    near = [g for g in want[0]]
    hist = [(int(gid[far]), 0.25)]
    if near:
        hist.append((near[0], 0.5))
    hist.append((99999, 0.75))
    hist.sort()
    h_off = np.zeros(n_local + 1, np.int64)
    h_off[1:] = len(hist)
    h_gid = np.array([g for g, _ in hist], np.int64)
    h_lam = np.array([l for _, l in hist])
    off, pj, pl, missing, _ = neighbors.build_rows(x, n_local, n, gid, diam, skin, h_off, h_gid, h_lam)
    assert missing == 1
    got = rows_as_gids(off, pj, gid)
    assert got[0] == sorted(set(want[0]) | {int(gid[far])})
    assert got[1:] == want[1:]
    lam0 = dict(zip(got[0], pl[off[0]:off[1]]))
    assert lam0[int(gid[far])] == 0.25
    if near:
        assert lam0[near[0]] == 0.5
    assert sum(v > 0 for v in lam0.values()) == len(hist) - 1
    assert np.all(pl[off[1]:] == 0.0)


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_build_rows_history_sparse_grid_and_crowded_cells(dim):
    """Rows against brute force where the build takes its less common paths: a cloud spread so
    wide that the cell grid is searched instead of indexed, a crowd of coincident spheres in
    one cell (the longest row), histories out of gid order with repeated, far and absent
    partners (lambda: the largest of a partner's entries), and the entry cap."""
    rng = np.random.default_rng(70 + dim)
    n, n_local = 120, 90
    x = np.concatenate([rng.normal(size=(60, dim)),                 # a dense core
                        rng.uniform(-1e7, 1e7, size=(50, dim)),     # far apart: sparse grid
                        np.zeros((10, dim))])                       # coincident: one full cell
    x = x[rng.permutation(n)]
    diam = rng.uniform(0.6, 1.3, size=n)
    gid = (rng.permutation(n) * 7 + 3).astype(np.int64)
    skin = 0.3
    want = brute_rows(x, n_local, gid, diam, skin)
    h_off = np.zeros(n_local + 1, np.int64)
    h_gid, h_lam, best, missing_want = [], [], [], 0
    for i in range(n_local):
        lam_of = {}
        for _ in range(int(rng.integers(0, 7))):
            if rng.random() < 0.85:
                g = int(gid[rng.integers(0, n)])
                if g == gid[i]:
                    continue
                lam_of[g] = max(lam_of.get(g, 0.0), lam := float(rng.uniform(0.1, 1.0)))
            else:
                g, lam = 10 ** 9 + int(rng.integers(0, 3)), 0.5  # present nowhere
                missing_want += 1
            h_gid.append(g)
            h_lam.append(lam)
        h_off[i + 1] = len(h_gid)
        best.append(lam_of)
    h_gid, h_lam = np.array(h_gid, np.int64), np.array(h_lam)
    off, pj, pl, missing, _ = neighbors.build_rows(x, n_local, n, gid, diam, skin, h_off, h_gid, h_lam)
    assert missing == missing_want
    got = rows_as_gids(off, pj, gid)
    for i in range(n_local):
        assert got[i] == sorted(set(want[i]) | set(best[i])), f"row {i}"
        lam = dict(zip(got[i], pl[off[i]:off[i + 1]]))
        assert lam == {g: best[i].get(g, 0.0) for g in got[i]}, f"row {i}"
    assert max(len(r) for r in got) >= 9, "test set-up: the crowded cell gives long rows"
    # the entry cap: refused (-1), never truncated
    capped = neighbors.build_rows(x, n_local, n, gid, diam, skin, h_off, h_gid, h_lam,
                                  max_entries=int(off[-1]) - 1)
    assert capped[3] == -1
    exact = neighbors.build_rows(x, n_local, n, gid, diam, skin, h_off, h_gid, h_lam,
                                 max_entries=int(off[-1]))
    assert exact[3] == missing_want and np.array_equal(exact[1], pj)


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_spatial_order_is_a_stable_sort_by_cell(dim):
    """The counting sort (a grid of a few cells per particle) and the merge sort (a sparse
    grid) give the stable order of the cell keys."""
    rng = np.random.default_rng(90 + dim)
    for spread in (0.5, 5.0, 1e6):
        x = rng.normal(size=(300, dim)) * spread
        keys, _, _ = neighbors.cell_keys(x, 300, 1.3)
        assert np.array_equal(neighbors.spatial_order(x, 300, 1.3), np.argsort(keys, kind="mergesort"))
    assert neighbors.spatial_order(np.zeros((0, dim)), 0, 1.3).shape == (0,)


def test_missing_partners_is_the_sorted_set_difference():
    """The history partners a rank must request: np.setdiff1d's result (sorted, unique), by the
    byte table when the gids span a narrow range and by binary search when they are sparse;
    repeated and absent partners, empty inputs."""
    rng = np.random.default_rng(7)
    for span, n_present, n_hist in ((500, 300, 900), (10 ** 12, 300, 900), (50, 0, 40),
                                    (50, 40, 0), (2 ** 40, 1, 3)):
        present = rng.choice(span, size=n_present, replace=False).astype(np.int64)
        hist = np.concatenate([rng.choice(present, size=n_hist // 2) if n_present else
                               np.zeros(0, np.int64),
                               rng.integers(0, span, size=n_hist - n_hist // 2)]).astype(np.int64)
        got = neighbors.missing_partners(present, hist)
        want = np.setdiff1d(hist, present)
        assert got.dtype == np.int64 and np.array_equal(got, want), (span, n_present, n_hist)
    # the dense path is taken for a narrow span, the search for a wide one (both above)
    assert 500 <= neighbors.DENSE_SPAN * 1200 and 10 ** 12 > neighbors.DENSE_SPAN * 1200


def test_the_reduction_reads_values_overflow_and_non_finite_maxima():
    """Reduction.reduce reads the reduced buffers once: exact values by name, NaN where a sum
    met a NaN (``overflowed``), and whether every maximum is finite (Inf or NaN is not)."""
    from mpipack.parallel.comm import Comm
    from mpipack.parallel.reduction import Reduction

    red = Reduction().add_exact("b", [("s", 2)]).add_count("c").add_max("m", [("top", 2)])
    comm = Comm.serial()
    for s0, s1, tops, overflowed, finite in [(1.5, -2.25, (0.5, 3.0), False, True),
                                           (np.nan, 1.0, (0.5, 3.0), True, True),
                                           (1.0, 1.0, (np.inf, 0.0), False, False),
                                           (1.0, 1.0, (0.0, np.nan), False, False)]:
        acc = red.begin().acc("b")
        exactsum.accumulate(np.array([s0, 0.0]), acc, 0)
        exactsum.accumulate(np.array([s1]), acc, 1)
        red.set_count("c", 7)
        red.maxima("m")[:] = tops
        red.reduce(comm)
        assert red.overflowed() is overflowed and red.all_maxima_finite() is finite
        assert red.count("c") == 7
        assert np.isnan(red.value("s", 0)) if overflowed else red.value("s", 0) == s0
        assert red.value("s", 1) == s1 and red.values("s")[1] == s1
        if finite:
            assert red.max("top", 1) == 3.0
