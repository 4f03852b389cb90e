"""Verlet pair rows with a skin, built from a cell list. Serial array code: no MPI.

A local particle i gets a row of partners j (local or ghost) holding

    every j with |X_i - X_j| < d_ij + skin          (candidates for a new contact), and
    every j of i's pair history (lambda_ij > 0),    however far away j is,

sorted by partner global id, with lambda from the history (0 for new pairs). The row stays
valid until some particle has moved more than skin/2 since the build: two particles that were
further apart than d_ij + skin cannot overlap before that.

Cells: size h = max diameter + skin. Cell coordinates become one int64 key per particle; the
particles are sorted by key (a counting sort over a grid of at most 16 cells a particle, else a
merge sort) and a cell's members are found by the grid's index or by binary search, so memory
is O(particles) however sparse or spread out the cloud is.
"""

import numpy as np

from mpipack.jit import njit


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
    """Integer cell coordinates of x[:n] in cells of size h (or larger: see below).

    Returns (keys int64 (n,), lo float64 (b,), dims int64 (b,)); key = sum_k c_k * stride_k.
    A cloud so spread out that the cell count would overflow the int64 key (more than 2^62
    cells: in 3D an extent of ~1.6e6 cells per axis) gets cells doubled in size until it
    fits: the 3^b cells around a sphere then still hold every partner within h, so the rows
    stay exact (without it the keys wrapped and far-apart cells aliased, losing pairs).
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
    if n > 0:
        while True:
            cells = 1.0
            for k in range(b):
                cells *= np.floor((hi[k] - lo[k]) / h) + 1.0
            if cells <= 2.0 ** 62 or not cells < np.inf:  # (inf or NaN coordinates: as before)
                break
            h *= 2.0
        for k in range(b):
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
def dense_cells(dims, n):
    """The number of cells of the grid ``dims`` when it is small enough to index directly (at
    most 16 n + 64 cells for n particles: a spread start has up to ~10 cells a particle, and an
    index of int32 costs 4 bytes a cell), else 0 (a sparse cloud: cells found by search)."""
    limit = 16 * n + 64
    n_cells = np.int64(1)
    for k in range(dims.shape[0]):
        if dims[k] > limit or n_cells * dims[k] > limit:
            return np.int64(0)
        n_cells *= dims[k]
    return n_cells


@njit(cache=True)
def _cell_index(keys, n_cells_dense):
    """Particles sorted by cell key, and a way to find each cell's members.

    Returns (order, skeys, cell_start): order sorts keys (stably), skeys = keys[order]; if
    n_cells_dense > 0, cell_start int32 (n_cells_dense+1,) gives cell c's members as
    order[cell_start[c]:cell_start[c+1]] (a counting sort, O(n)); otherwise cell_start is
    empty and a cell's members are found by binary search in skeys (for sparse clouds, where a
    dense grid would not fit in memory).
    """
    n = keys.shape[0]
    if n_cells_dense > 0:
        cell_start = np.zeros(n_cells_dense + 1, dtype=np.int32)
        for i in range(n):
            cell_start[keys[i] + 1] += 1
        for c in range(n_cells_dense):
            cell_start[c + 1] += cell_start[c]
        # place each particle at its cell's next free slot (cell_start[c] walks to the end of
        # cell c, which is the start of c + 1), then shift the starts back by one cell
        order = np.empty(n, dtype=np.int64)
        for i in range(n):
            c = keys[i]
            order[cell_start[c]] = i
            cell_start[c] += 1
        for c in range(n_cells_dense, 0, -1):
            cell_start[c] = cell_start[c - 1]
        cell_start[0] = 0
        return order, keys[order], cell_start
    order = np.argsort(keys, kind="mergesort")
    return order, keys[order], np.zeros(0, dtype=np.int32)


@njit(cache=True)
def _max_occupancy(skeys):
    """The most particles in one cell: the longest run of equal sorted keys."""
    most = 0
    run = 0
    for q in range(skeys.shape[0]):
        run = run + 1 if q > 0 and skeys[q] == skeys[q - 1] else 1
        if run > most:
            most = run
    return most


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

    The particles' positions, diameters and gids are copied in cell order (row-major cell
    keys), so the 3 cells along the last axis of each of the 3^(b-1) neighbour cell rows are
    one contiguous run of that copy: a sphere's candidates are 3^(b-1) runs, read in place.
    Each row is assembled in buffers sized once for the longest possible row (3^b cells of
    the fullest occupancy, at most all particles, plus the longest history) and sorted by
    partner gid; history partners already among the candidates take their lambda, the others
    (far partners) are inserted. No buffer is reallocated inside the candidate loop: growable
    buffers there made the build 4x slower (measured: docs/research/convergence.md, section 3o).
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
    n_cells = dense_cells(dims, n_total)
    dense = n_cells > 0
    order, skeys, cell_start = _cell_index(keys, n_cells)
    # positions, diameters and gids in cell order
    xs = np.empty((n_total, b))
    ds = np.empty(n_total)
    gs = np.empty(n_total, dtype=np.int64)
    for q in range(n_total):
        j = order[q]
        for k in range(b):
            xs[q, k] = x[j, k]
        ds[q] = diam[j]
        gs[q] = gid[j]
    n_rows_nb = 3 ** (b - 1)
    offs = np.empty((n_rows_nb, b), dtype=np.int64)
    for m in range(n_rows_nb):
        t = m
        for k in range(b - 1):
            offs[m, k] = t % 3 - 1
            t //= 3
        offs[m, b - 1] = 0
    # the longest row: every particle of the 3^b cells around (at most all of them), plus the
    # longest history
    most_hist = 0
    for i in range(n_local):
        if hist_offsets[i + 1] - hist_offsets[i] > most_hist:
            most_hist = hist_offsets[i + 1] - hist_offsets[i]
    row_cap = min(3 * n_rows_nb * _max_occupancy(skeys), n_total) + most_hist + 1
    row_g = np.empty(row_cap, dtype=np.int64)
    row_j = np.empty(row_cap, dtype=np.int64)
    row_l = np.empty(row_cap)
    # the rank sort's output, swapped with row_g, row_j
    row_g2 = np.empty(row_cap, dtype=np.int64)
    row_j2 = np.empty(row_cap, dtype=np.int64)
    # gid -> index lookup, built only when a history partner is not among the candidates
    sgid = np.empty(0, dtype=np.int64)
    gorder = np.empty(0, dtype=np.int64)
    have_lookup = False

    cap = min(max(16, n_local * 8), max(16, max_entries))
    pair_j = np.empty(cap, dtype=np.int32)
    pair_lambda = np.empty(cap)
    coord = np.empty(b, dtype=np.int64)
    # the runs of the cell order holding the candidates of the current cell
    run_start = np.empty(n_rows_nb, dtype=np.int64)
    run_end = np.empty(n_rows_nb, dtype=np.int64)
    n_runs = 0
    run_key = np.int64(-1)
    last = b - 1
    missing = 0
    pos = 0
    for i in range(n_local):
        cnt = 0
        if keys[i] != run_key:
            run_key = keys[i]
            t = keys[i]
            for k in range(b - 1, -1, -1):
                coord[k] = t % dims[k]
                t //= dims[k]
            c_lo = max(coord[last] - 1, 0)
            c_hi = min(coord[last] + 1, dims[last] - 1)
            n_runs = 0
            for m in range(n_rows_nb):
                base = np.int64(0)
                ok = True
                for k in range(b - 1):
                    c = coord[k] + offs[m, k]
                    if c < 0 or c >= dims[k]:
                        ok = False
                        break
                    base = base * dims[k] + c
                if not ok:
                    continue
                base = base * dims[last]
                if dense:
                    s0 = np.int64(cell_start[base + c_lo])
                    s1 = np.int64(cell_start[base + c_hi + 1])
                else:
                    s0 = _searchsorted_left(skeys, base + c_lo)
                    s1 = _searchsorted_left(skeys, base + c_hi + 1)
                if s1 > s0:
                    run_start[n_runs] = s0
                    run_end[n_runs] = s1
                    n_runs += 1
        di = diam[i]
        # every candidate's place in the cell order is written, and kept (cnt advances) when
        # it is within reach: no branch to mispredict in the hottest loop
        for r in range(n_runs):
            for q in range(run_start[r], run_end[r]):
                r2 = 0.0
                for k in range(b):
                    dx = x[i, k] - xs[q, k]
                    r2 += dx * dx
                rc = 0.5 * (di + ds[q]) + skin
                row_j[cnt] = q
                cnt += np.int64(r2 < rc * rc)
        kept = 0
        for c in range(cnt):
            q = row_j[c]
            j = order[q]
            if j != i:
                row_g[kept] = gs[q]
                row_j[kept] = j
                kept += 1
        cnt = kept
        if cnt <= _SORT_SHORT and _rank_sort(row_g, row_j, cnt, row_g2, row_j2):
            row_g, row_g2 = row_g2, row_g
            row_j, row_j2 = row_j2, row_j
        else:
            _sort_row(row_g, row_j, cnt)
        for q in range(cnt):
            row_l[q] = 0.0
        # the history (in gid order, as ``history`` gives it) merged into the sorted row
        q = 0
        g_prev = np.int64(-1)
        for e in range(hist_offsets[i], hist_offsets[i + 1]):
            g = hist_gid[e]
            if g < g_prev:  # not in gid order (a history read from elsewhere): search afresh
                q = 0
            g_prev = g
            while q < cnt and row_g[q] < g:
                q += 1
            if q < cnt and row_g[q] == g:  # a candidate (or a repeated partner): the larger lambda
                if hist_lambda[e] > row_l[q]:
                    row_l[q] = hist_lambda[e]
                continue
            if not have_lookup:
                gorder = np.argsort(gid[:n_total])
                sgid = gid[:n_total][gorder]
                have_lookup = True
            s = _searchsorted_left(sgid, g)
            if s >= n_total or sgid[s] != g:
                missing += 1
                continue
            for c in range(cnt, q, -1):
                row_g[c] = row_g[c - 1]
                row_j[c] = row_j[c - 1]
                row_l[c] = row_l[c - 1]
            row_g[q] = g
            row_j[q] = gorder[s]
            row_l[q] = hist_lambda[e]
            cnt += 1
        if pos + cnt > max_entries:
            return pair_offsets, pair_j[:0].copy(), pair_lambda[:0].copy(), -1
        if pos + cnt > cap:
            cap = min(max(2 * cap, pos + cnt), max_entries)
            pair_j = _grow_i32(pair_j, cap)
            pair_lambda = _grow_f(pair_lambda, cap)
        for q in range(cnt):
            pair_j[pos + q] = row_j[q]
            pair_lambda[pos + q] = row_l[q]
        pos += cnt
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


# a row of at most this many entries is sorted by ranks (``_rank_sort``), a longer one by
# ``_sort_row``
_SORT_SHORT = 48


@njit(cache=True, inline="always")
def _rank_sort(g, j, n, g_out, j_out):
    """g[:n] ascending into g_out[:n], j alike into j_out, each entry placed at its rank (the
    number of smaller keys: n^2 comparisons with no branch, quicker than an insertion sort's
    mispredicted exits for a row of ~4-14 entries, docs/benchmarks.md "Cheaper rebuilds").
    Returns False, with g_out and j_out unfinished, if two keys are equal (their ranks are then
    not all distinct: the ranks' sum falls short of 0 + 1 + ... + n-1)."""
    rank_sum = 0
    for a in range(n):
        ga = g[a]
        r = 0
        for c in range(n):
            r += np.int64(g[c] < ga)
        g_out[r] = ga
        j_out[r] = j[a]
        rank_sum += r
    return rank_sum == n * (n - 1) // 2


@njit(cache=True)
def _sort_row(g, j, n):
    """Sort g[:n] ascending, permuting j alike (insertion sort; argsort when long: a start
    with many coincident spheres has rows of thousands)."""
    if n > _SORT_SHORT:
        o = np.argsort(g[:n])
        g[:n] = g[:n][o]
        j[:n] = j[:n][o]
        return
    for a in range(1, n):
        kg = g[a]
        kj = j[a]
        c = a - 1
        while c >= 0 and g[c] > kg:
            g[c + 1] = g[c]
            j[c + 1] = j[c]
            c -= 1
        g[c + 1] = kg
        j[c + 1] = kj


@njit(cache=True)
def spatial_order(x, n, h):
    """A permutation of x[:n] that visits cells of size h in row-major order (cache locality),
    stable within a cell: the rows' build's own sort (``_cell_index``)."""
    keys, lo, dims = cell_keys(x, n, h)
    order, _, _ = _cell_index(keys, dense_cells(dims, n))
    return order


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
    # every entry is written at the next free place, and kept (pos advances) when lambda > 0:
    # no branch to mispredict (about a third of a packing's entries are contacts)
    n_pairs = pair_offsets[n_local]
    hist_offsets = np.empty(n_local + 1, dtype=np.int64)
    hist_gid = np.empty(n_pairs, dtype=np.int64)
    hist_lambda = np.empty(n_pairs)
    hist_offsets[0] = 0
    pos = 0
    for i in range(n_local):
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            hist_gid[pos] = gid[pair_j[e]]
            hist_lambda[pos] = pair_lambda[e]
            pos += np.int64(pair_lambda[e] > 0.0)
        hist_offsets[i + 1] = pos
    hist_gid = hist_gid[:pos].copy()
    hist_lambda = hist_lambda[:pos].copy()
    return hist_offsets, hist_gid, hist_lambda


# a gid span up to this many times the number of gids involved is marked in a dense table
# (one byte per gid); a wider one is searched in the sorted present gids
DENSE_SPAN = 64


@njit(cache=True)
def missing_partners(present, hist_gid):
    """Sorted unique gids of ``hist_gid`` that are not in ``present`` (both int64): the
    history partners a rank still has to request (``np.setdiff1d(hist_gid, present)``).

    When the gids span at most DENSE_SPAN times their number, every present gid is marked in
    a byte table and each partner looked up in it (O(n); measured 1.8 ms of np.setdiff1d's
    hash-based uniques per rebuild at 3D N = 20000 on 2 ranks); else binary search in the
    sorted present gids. The few missing ones are then sorted.
    """
    n_h = hist_gid.shape[0]
    if n_h == 0:
        return np.empty(0, dtype=np.int64)
    lo = hist_gid[0]
    hi = hist_gid[0]
    for v in hist_gid:
        lo = min(lo, v)
        hi = max(hi, v)
    for v in present:
        lo = min(lo, v)
        hi = max(hi, v)
    out = np.empty(n_h, dtype=np.int64)
    n = 0
    if hi - lo + 1 <= DENSE_SPAN * (n_h + present.shape[0]):
        mark = np.zeros(hi - lo + 1, dtype=np.uint8)  # 1: present, 2: already reported
        for v in present:
            mark[v - lo] = 1
        for v in hist_gid:
            if mark[v - lo] == 0:
                mark[v - lo] = 2
                out[n] = v
                n += 1
        return np.sort(out[:n])
    spresent = np.sort(present)
    for v in hist_gid:
        s = _searchsorted_left(spresent, v)
        if s >= spresent.shape[0] or spresent[s] != v:
            out[n] = v
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
