"""Verlet pair rows with a skin, built from a cell list. Serial array code: no MPI.

A local particle i gets a row of partners j (local or ghost) holding

    every j with |X_i - X_j| < d_ij + skin          (candidates for a new contact), and
    every j of i's pair history (lambda_ij > 0),    however far away j is,

sorted by partner global id, with lambda from the history (0 for new pairs). The row stays
valid until some particle has moved more than skin/2 since the build: two particles that were
further apart than d_ij + skin cannot overlap before that.

Cells: size h = max diameter + skin. Cell coordinates become one int64 key per particle; the
particles are sorted by key and a cell's members are found by binary search, so memory is
O(particles) however sparse or spread out the cloud is.
"""

import numpy as np
from numba import njit


@njit(cache=True)
def _searchsorted_left(a, v):
    lo = 0
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def cell_keys(x, n, h):
    """Integer cell coordinates of x[:n] in cells of size h.

    Returns (keys int64 (n,), lo float64 (b,), dims int64 (b,)); key = sum_k c_k * stride_k.
    """
    b = x.shape[1]
    lo = np.full(b, np.inf)
    hi = np.full(b, -np.inf)
    for i in range(n):
        for k in range(b):
            v = x[i, k]
            if v < lo[k]:
                lo[k] = v
            if v > hi[k]:
                hi[k] = v
    dims = np.ones(b, dtype=np.int64)
    for k in range(b):
        if n > 0:
            dims[k] = np.int64((hi[k] - lo[k]) / h) + 1
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        key = np.int64(0)
        for k in range(b):
            c = np.int64((x[i, k] - lo[k]) / h)
            if c >= dims[k]:
                c = dims[k] - 1
            key = key * dims[k] + c
        keys[i] = key
    return keys, lo, dims


@njit(cache=True)
def _cell_index(keys, n_cells_dense):
    """Particles sorted by cell key, and a way to find each cell's members.

    Returns (order, skeys, cell_start): order sorts keys; if n_cells_dense > 0, cell_start
    (n_cells_dense+1,) gives cell c's members as order[cell_start[c]:cell_start[c+1]] (a
    counting sort, O(n)); otherwise cell_start is empty and members are found by binary
    search in skeys (for sparse clouds, where a dense grid would not fit in memory).
    """
    n = keys.shape[0]
    if n_cells_dense > 0:
        cell_start = np.zeros(n_cells_dense + 1, dtype=np.int64)
        for i in range(n):
            cell_start[keys[i] + 1] += 1
        for c in range(n_cells_dense):
            cell_start[c + 1] += cell_start[c]
        fill = cell_start[:-1].copy()
        order = np.empty(n, dtype=np.int64)
        for i in range(n):
            c = keys[i]
            order[fill[c]] = i
            fill[c] += 1
        return order, keys[:0].copy(), cell_start
    order = np.argsort(keys)
    return order, keys[order], np.zeros(0, dtype=np.int64)


@njit(cache=True, inline="always")
def _cell_range(nkey, skeys, cell_start):
    if cell_start.shape[0] > 0:
        return cell_start[nkey], cell_start[nkey + 1]
    s = _searchsorted_left(skeys, nkey)
    e = s
    while e < skeys.shape[0] and skeys[e] == nkey:
        e += 1
    return s, e


@njit(cache=True, inline="always")
def _build_rows(b, x, n_local, n_total, gid, diam, skin, hist_offsets, hist_gid, hist_lambda,
                max_entries):
    """Pair rows of the local particles.

    x (n_total, b) with locals first; gid int64, diam float64 (n_total,);
    hist_offsets (n_local+1,), hist_gid int64, hist_lambda float64: local particle i's history
    is entries hist_offsets[i]:hist_offsets[i+1] (partner gid, lambda > 0).

    Returns (pair_offsets int64 (n_local+1,), pair_j int32 (n_pairs,), pair_lambda (n_pairs,),
    missing) where missing is the number of history partners not present in x (they must be
    made ghosts before the build; the caller treats missing > 0 as an error). If the rows would
    hold more than max_entries entries the build stops early and missing is -1: a start so
    dense that the rows would not fit in memory is reported, not attempted.
    """
    pair_offsets = np.zeros(n_local + 1, dtype=np.int64)
    if n_local == 0:
        return pair_offsets, np.empty(0, dtype=np.int32), np.empty(0), 0
    dmax = 0.0
    for i in range(n_total):
        if diam[i] > dmax:
            dmax = diam[i]
    h = dmax + skin
    keys, lo, dims = cell_keys(x, n_total, h)
    n_cells = np.int64(1)
    dense = True
    for k in range(b):
        if dims[k] > 4 * n_total + 64 or n_cells * dims[k] > 4 * n_total + 64:
            dense = False
            break
        n_cells *= dims[k]
    order, skeys, cell_start = _cell_index(keys, n_cells if dense else 0)
    # gid -> index lookup, needed only for history partners
    n_hist = hist_offsets[n_local]
    if n_hist > 0:
        gorder = np.argsort(gid[:n_total])
        sgid = gid[:n_total][gorder]
    else:
        gorder = np.empty(0, dtype=np.int64)
        sgid = np.empty(0, dtype=np.int64)

    n_nb = 3 ** b
    offs = np.empty((n_nb, b), dtype=np.int64)
    for m in range(n_nb):
        t = m
        for k in range(b):
            offs[m, k] = t % 3 - 1
            t //= 3

    cap = min(max(16, n_local * 8), max(16, max_entries))
    pair_j = np.empty(cap, dtype=np.int32)
    pair_lambda = np.empty(cap)
    tmp_cap = 64
    tmp_j = np.empty(tmp_cap, dtype=np.int64)
    tmp_g = np.empty(tmp_cap, dtype=np.int64)
    tmp_l = np.empty(tmp_cap)
    coord = np.empty(b, dtype=np.int64)
    missing = 0
    pos = 0
    for i in range(n_local):
        cnt = 0
        t = keys[i]
        for k in range(b - 1, -1, -1):
            coord[k] = t % dims[k]
            t //= dims[k]
        for m in range(n_nb):
            nkey = np.int64(0)
            ok = True
            for k in range(b):
                c = coord[k] + offs[m, k]
                if c < 0 or c >= dims[k]:
                    ok = False
                    break
                nkey = nkey * dims[k] + c
            if not ok:
                continue
            s, e_end = _cell_range(nkey, skeys, cell_start)
            for s in range(s, e_end):
                j = order[s]
                if j == i:
                    continue
                r2 = 0.0
                for k in range(b):
                    dx = x[i, k] - x[j, k]
                    r2 += dx * dx
                rc = 0.5 * (diam[i] + diam[j]) + skin
                if r2 < rc * rc:
                    if cnt == tmp_cap:
                        tmp_cap *= 2
                        tmp_j = _grow_i(tmp_j, tmp_cap)
                        tmp_g = _grow_i(tmp_g, tmp_cap)
                        tmp_l = _grow_f(tmp_l, tmp_cap)
                    tmp_j[cnt] = j
                    tmp_g[cnt] = gid[j]
                    tmp_l[cnt] = 0.0
                    cnt += 1
        for e in range(hist_offsets[i], hist_offsets[i + 1]):
            g = hist_gid[e]
            s = _searchsorted_left(sgid, g)
            if s >= n_total or sgid[s] != g:
                missing += 1
                continue
            if cnt == tmp_cap:
                tmp_cap *= 2
                tmp_j = _grow_i(tmp_j, tmp_cap)
                tmp_g = _grow_i(tmp_g, tmp_cap)
                tmp_l = _grow_f(tmp_l, tmp_cap)
            tmp_j[cnt] = gorder[s]
            tmp_g[cnt] = g
            tmp_l[cnt] = hist_lambda[e]
            cnt += 1
        # sort the row by partner gid (insertion sort: rows are short), merge duplicates (a
        # history partner that is also a candidate keeps its lambda)
        _sort_row(tmp_g, tmp_j, tmp_l, cnt)
        if pos + cnt > max_entries:
            return pair_offsets, pair_j[:0].copy(), pair_lambda[:0].copy(), -1
        if pos + cnt > cap:
            cap = min(max(2 * cap, pos + cnt), max_entries)
            pair_j = _grow_i32(pair_j, cap)
            pair_lambda = _grow_f(pair_lambda, cap)
        for q in range(cnt):
            if q > 0 and tmp_g[q] == tmp_g[q - 1]:
                if tmp_l[q] > pair_lambda[pos - 1]:
                    pair_lambda[pos - 1] = tmp_l[q]
                continue
            pair_j[pos] = tmp_j[q]
            pair_lambda[pos] = tmp_l[q]
            pos += 1
        pair_offsets[i + 1] = pos
    return pair_offsets, pair_j[:pos].copy(), pair_lambda[:pos].copy(), missing


@njit(cache=True)
def _build_rows_1(x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries):
    return _build_rows(1, x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries)


@njit(cache=True)
def _build_rows_2(x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries):
    return _build_rows(2, x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries)


@njit(cache=True)
def _build_rows_3(x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries):
    return _build_rows(3, x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries)


def build_rows(x, n_local, n_total, gid, diam, skin, hist_offsets, hist_gid, hist_lambda,
               max_entries=2 ** 62):
    """Pair rows of the local particles (compiled per dimension; see ``_build_rows``).

    Returns (pair_offsets int64 (n_local+1,), pair_j int32 (n_pairs,), pair_lambda (n_pairs,),
    missing); missing = -1 when the rows would exceed max_entries entries.
    """
    f = (_build_rows_1, _build_rows_2, _build_rows_3)[x.shape[1] - 1]
    return f(x, n_local, n_total, gid, diam, skin, hist_offsets, hist_gid, hist_lambda,
             np.int64(max_entries))


@njit(cache=True)
def _sort_row(g, j, lam, n):
    """Sort g[:n] ascending, permuting j and lam alike (insertion sort; argsort when long)."""
    if n > 48:
        o = np.argsort(g[:n])
        g[:n] = g[:n][o]
        j[:n] = j[:n][o]
        lam[:n] = lam[:n][o]
        return
    for a in range(1, n):
        kg = g[a]
        kj = j[a]
        kl = lam[a]
        c = a - 1
        while c >= 0 and g[c] > kg:
            g[c + 1] = g[c]
            j[c + 1] = j[c]
            lam[c + 1] = lam[c]
            c -= 1
        g[c + 1] = kg
        j[c + 1] = kj
        lam[c + 1] = kl


@njit(cache=True)
def spatial_order(x, n, h):
    """A permutation of x[:n] that visits cells of size h in row-major order (cache locality)."""
    keys, lo, dims = cell_keys(x, n, h)
    return np.argsort(keys, kind="mergesort")


@njit(cache=True)
def _grow_i(a, n):
    out = np.empty(n, dtype=np.int64)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def _grow_i32(a, n):
    out = np.empty(n, dtype=np.int32)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def _grow_f(a, n):
    out = np.empty(n)
    out[: a.shape[0]] = a
    return out


@njit(cache=True)
def history(n_local, gid, pair_offsets, pair_j, pair_lambda):
    """Pair history of each local particle: its partners with lambda > 0.

    Returns (hist_offsets int64 (n_local+1,), hist_gid int64, hist_lambda float64), partners in
    gid order. This is what travels with a particle when it migrates.
    """
    hist_offsets = np.zeros(n_local + 1, dtype=np.int64)
    n = 0
    for e in range(pair_offsets[n_local]):
        if pair_lambda[e] > 0.0:
            n += 1
    hist_gid = np.empty(n, dtype=np.int64)
    hist_lambda = np.empty(n)
    pos = 0
    for i in range(n_local):
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            if pair_lambda[e] > 0.0:
                hist_gid[pos] = gid[pair_j[e]]
                hist_lambda[pos] = pair_lambda[e]
                pos += 1
        hist_offsets[i + 1] = pos
    return hist_offsets, hist_gid, hist_lambda


@njit(cache=True)
def missing_partners(n_total, gid, hist_gid):
    """Sorted unique history partner gids that are not among gid[:n_total]."""
    sgid = np.sort(gid[:n_total])
    out = np.empty(hist_gid.shape[0], dtype=np.int64)
    n = 0
    for e in range(hist_gid.shape[0]):
        g = hist_gid[e]
        s = _searchsorted_left(sgid, g)
        if s >= n_total or sgid[s] != g:
            out[n] = g
            n += 1
    return np.unique(out[:n])


@njit(cache=True)
def max_displacement2(x, x_build, n_local):
    """max_i |x_i - x_build_i|^2 over local particles."""
    m = 0.0
    for i in range(n_local):
        s = 0.0
        for k in range(x.shape[1]):
            d = x[i, k] - x_build[i, k]
            s += d * d
        if s > m:
            m = s
    return m
