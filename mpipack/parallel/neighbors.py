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

The build tests each pair once, from the forward half of the cells around a particle, and
gives with the rows each entry's mirror (the partner's entry of the same pair), which the
fire-al pass's half list reads (``_build_rows_once``); a dense start's rows are made one row at
a time (``_build_rows_sorted``). Both give the same rows, bit for bit.
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
def _cell_order(b, x, n_total, gid, diam, skin):
    """The build's cells (size h = max diameter + skin) and the particles in cell order.

    Returns (keys int64 (n_total,), dims int64 (b,), dense, order, skeys, cell_start, xs
    (n_total, b), ds, gs): ``_cell_index``'s order of the keys, and the positions, diameters and
    gids copied in that order (row-major cell keys, so that the 3 cells along the last axis of a
    row of cells are one contiguous run of the copy)."""
    dmax = 0.0
    for i in range(n_total):
        if diam[i] > dmax:
            dmax = diam[i]
    keys, lo, dims = cell_keys(x, n_total, dmax + skin)
    n_cells = dense_cells(dims, n_total)
    order, skeys, cell_start = _cell_index(keys, n_cells)
    xs = np.empty((n_total, b))
    ds = np.empty(n_total)
    gs = np.empty(n_total, dtype=np.int64)
    for q in range(n_total):
        j = order[q]
        for k in range(b):
            xs[q, k] = x[j, k]
        ds[q] = diam[j]
        gs[q] = gid[j]
    return keys, dims, n_cells > 0, order, skeys, cell_start, xs, ds, gs


@njit(cache=True, inline="always")
def _stencil(b, forward):
    """The rows of cells (offsets along the first b - 1 axes, 0 along the last) whose 3 cells
    along the last axis hold a cell's neighbours: all 3^(b-1) of them; or, ``forward``, the
    cell's own row first, then the rows after it in key order (their first nonzero offset from
    axis 0, the key's most significant, is +1), so that each pair of neighbouring cells is met
    from one of its two cells. Returns offs int64 (rows, b)."""
    n_all = 3 ** (b - 1)
    offs = np.zeros(((n_all + 1) // 2 if forward else n_all, b), dtype=np.int64)
    o = np.empty(b, dtype=np.int64)
    n = 1 if forward else 0  # (forward: row 0 is the cell's own, all offsets 0)
    for m in range(n_all):
        t = m
        first = 0
        for k in range(b - 1):
            o[k] = t % 3 - 1
            t //= 3
        for k in range(b - 2, -1, -1):
            if o[k] != 0:
                first = o[k]
        if forward and first <= 0:
            continue
        for k in range(b - 1):
            offs[n, k] = o[k]
        n += 1
    return offs


@njit(cache=True, inline="always")
def _cell_runs(b, key, dims, dense, cell_start, skeys, offs, forward, coord, run_start, run_end):
    """The runs of the cell order that hold the particles of the cells around the cell ``key``:
    for each row of ``offs`` (``_stencil``) its cells c - 1 .. c + 1 along the last axis (with
    ``forward``, row 0 from c: the cell itself and the next), empty runs left out but row 0's
    (forward: it holds the cell's own particles). Returns the number of runs written."""
    t = key
    for k in range(b - 1, -1, -1):
        coord[k] = t % dims[k]
        t //= dims[k]
    last = b - 1
    c_hi = min(coord[last] + 1, dims[last] - 1)
    n_runs = 0
    for m in range(offs.shape[0]):
        c_lo = coord[last] if forward and m == 0 else max(coord[last] - 1, 0)
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
        if s1 > s0 or (forward and m == 0):
            run_start[n_runs] = s0
            run_end[n_runs] = s1
            n_runs += 1
    return n_runs


# a row of at most this many entries finds a history partner's place by counting
# (``_merge_history``), a longer one by walking from the previous partner's
_COUNT_ROW = 32


@njit(cache=True)
def _merge_history(i, cnt, row_g, row_j, row_l, row_t, hist_offsets, hist_gid, hist_lambda, sgid,
                   gorder, missing):
    """Local particle i's history (in gid order, as ``history`` gives it) merged into its row
    (row_g, row_j, row_l, row_t [:cnt], sorted by gid, lambda 0): a partner among the
    candidates takes the history's lambda (the larger of repeated ones), another is inserted
    (row_t -1) where the gid lookup finds it (sgid the gids sorted, gorder their indices, both
    (n_total,), filled by ``_gid_lookup`` once missing[1] = 1), else counted in missing[0].
    Returns the row's new length, or -1 when a partner must be inserted and the lookup is not
    filled: fill it (missing[1] = 1) and merge again (lambda's max is idempotent). (Kept small,
    the lookup's sort outside, so that LLVM inlines it into the builds' row loops: with the
    sort inside, called there, it made a 2D build 1.6 times as long.)"""
    q = 0
    g_prev = np.int64(-1)
    for e in range(hist_offsets[i], hist_offsets[i + 1]):
        g = hist_gid[e]
        if g < g_prev:  # not in gid order (a history read from elsewhere): search afresh
            q = 0
        g_prev = g
        if cnt <= _COUNT_ROW:
            # g's place in the sorted row: the number of smaller gids, counted without a
            # branch (the walk below stops at an unpredictable entry: a mispredicted exit for
            # every history partner)
            q = 0
            for c in range(cnt):
                q += np.int64(row_g[c] < g)
        else:
            while q < cnt and row_g[q] < g:
                q += 1
        if q < cnt and row_g[q] == g:  # a candidate (or a repeated partner): the larger lambda
            if hist_lambda[e] > row_l[q]:
                row_l[q] = hist_lambda[e]
            continue
        if missing[1] == 0:
            return -1
        s = _searchsorted_left(sgid, g)
        if s >= sgid.shape[0] or sgid[s] != g:
            missing[0] += 1
            continue
        for c in range(cnt, q, -1):
            row_g[c] = row_g[c - 1]
            row_j[c] = row_j[c - 1]
            row_l[c] = row_l[c - 1]
            row_t[c] = row_t[c - 1]
        row_g[q] = g
        row_j[q] = gorder[s]
        row_l[q] = hist_lambda[e]
        row_t[q] = -1
        cnt += 1
    return cnt


@njit(cache=True, inline="always")
def _row_buffers(n_total, cap_candidates, hist_offsets, n_local):
    """Row buffers sized once for the longest possible row: cap_candidates candidates (at
    most all particles) plus the longest history; (row_g, row_j, row_l, row_t) and two for the
    rank sort's work (``_rank_sort``)."""
    most_hist = 0
    for i in range(n_local):
        if hist_offsets[i + 1] - hist_offsets[i] > most_hist:
            most_hist = hist_offsets[i + 1] - hist_offsets[i]
    row_cap = min(cap_candidates, n_total) + most_hist + 1
    return (np.empty(row_cap, dtype=np.int64), np.empty(row_cap, dtype=np.int64), np.empty(row_cap),
            np.empty(row_cap, dtype=np.int64), np.empty(row_cap, dtype=np.int64),
            np.empty(row_cap, dtype=np.int64))


# ``_build_rows_once``'s answer when it leaves the build to ``_build_rows_sorted``
_FALL_BACK = -2
# the rows a build finds each pair once for: at most this many pairs per local sphere (a run's
# rows hold 3 - 6; a dense start's first build hundreds, which the one-row-at-a-time build makes
# in less memory)
PAIRS_ONCE_MAX = 24


@njit(cache=True, inline="always")
def _build_rows_once(b, x, n_local, n_total, gid, diam, skin, hist_offsets, hist_gid, hist_lambda,
                     max_entries):
    """Pair rows of the local particles, each pair found once, and each entry's mirror.

    Arguments and the rows as ``_build_rows_sorted`` (the same arrays, bit for bit); also
    mirror int64 (n_pairs,): the entry of the partner's row whose partner is this entry's
    particle, or -1 (a ghost partner, or none: a history partner that the other's history does
    not hold). Returns (pair_offsets, pair_j, pair_lambda, missing, mirror); missing is
    _FALL_BACK, and nothing else meaningful, for rows of more than PAIRS_ONCE_MAX pairs a
    sphere (or max_entries / 3 in all) and for a row with two entries of one gid.

    Each pair of particles in neighbouring cells is tested once, from the cell that comes
    first in ``_stencil``'s forward half (within a cell, from the particle first in cell
    order): |X_p - X_q|^2 < (d_pq / 2 + skin)^2 gives the same bits from either side. A pair
    is kept when one of its two is local; its two sides (tag 2k + side, k the pair) are
    scattered to the local particles' rows, each row sorted by partner gid and merged with its
    history as in ``_build_rows_sorted``, and the entry each side lands in is kept, so that a
    pair of two locals knows both of its entries without a search (``kernels.fire.pair_halves``).
    """
    keys, dims, dense, order, skeys, cell_start, xs, ds, gs = _cell_order(b, x, n_total, gid, diam, skin)
    offs = _stencil(b, True)
    local = np.empty(n_total, dtype=np.int64)
    for q in range(n_total):
        local[q] = np.int64(order[q] < n_local)
    # (its arrays hold about 60 B an entry against the other build's 40, BYTES_PER_ENTRY_PEAK:
    # at most 2/3 of max_entries, two entries a pair, keeps it within the memory guard)
    limit = min(PAIRS_ONCE_MAX * n_local, max_entries // 3)
    # pair k's two particles: ends[2k], ends[2k + 1]; room for the limit and one particle's
    # candidates past it, so never grown (grown inside the candidate loop, the build took 1.5
    # times as long); the pages past what is written are never touched
    ends = np.empty(2 * (limit + n_total), dtype=np.int32)
    coord = np.empty(b, dtype=np.int64)
    run_start = np.empty(offs.shape[0], dtype=np.int64)
    run_end = np.empty(offs.shape[0], dtype=np.int64)
    n_runs = 0
    run_key = np.int64(-1)
    n_pair = 0
    for q in range(n_total):
        if skeys[q] != run_key:
            run_key = skeys[q]
            n_runs = _cell_runs(b, run_key, dims, dense, cell_start, skeys, offs, True, coord, run_start,
                                run_end)
        dq = ds[q]
        lq = local[q]
        # every candidate is written, and kept (n_pair advances) when within reach and one of
        # the two is local: no branch to mispredict in the hottest loop
        for r in range(n_runs):
            for p in range(q + 1 if r == 0 else run_start[r], run_end[r]):
                r2 = 0.0
                for k in range(b):
                    dx = xs[q, k] - xs[p, k]
                    r2 += dx * dx
                rc = 0.5 * (dq + ds[p]) + skin
                ends[2 * n_pair] = q
                ends[2 * n_pair + 1] = p
                n_pair += np.int64(r2 < rc * rc) & (lq | local[p])
        if n_pair > limit:
            return (np.zeros(n_local + 1, dtype=np.int64), np.empty(0, dtype=np.int32), np.empty(0),
                    _FALL_BACK, np.empty(0, dtype=np.int64))
    # the pairs' ends scattered to the rows: tag t = 2k + side is the entry of particle
    # ends[t]'s row, whose partner is ends[t ^ 1]; a row's candidates (tag and the partner's
    # gid) in the order of k
    row_start = np.zeros(n_local + 2, dtype=np.int64)  # [n_local + 1]: the ghosts' ends, unused
    for t in range(2 * n_pair):
        a = order[ends[t]]
        ends[t] = a
        row_start[min(a, n_local) + 1] += 1
    for i in range(n_local):
        row_start[i + 1] += row_start[i]
    n_cand = row_start[n_local]
    cand_t = np.empty(n_cand, dtype=np.int64)
    cand_g = np.empty(n_cand, dtype=np.int64)
    fill = row_start[:n_local].copy()
    for t in range(2 * n_pair):
        a = ends[t]
        if a < n_local:
            c = fill[a]
            cand_t[c] = t
            cand_g[c] = gid[ends[t ^ 1]]
            fill[a] = c + 1
    most = 0
    for i in range(n_local):
        most = max(most, row_start[i + 1] - row_start[i])
    row_g, row_j, row_l, row_t, work_g, work_t = _row_buffers(n_total, most, hist_offsets, n_local)
    # gid -> index lookup, filled only when a history partner is not among the candidates (no
    # array is assigned inside the row loop: see ``ends``); missing: (count, lookup filled)
    sgid = np.empty(n_total, dtype=np.int64)
    gorder = np.empty(n_total, dtype=np.int64)
    missing = np.zeros(2, dtype=np.int64)
    pair_offsets = np.zeros(n_local + 1, dtype=np.int64)
    # the most the rows can hold (the candidates and every history entry; never grown)
    out_cap = min(n_cand + hist_offsets[n_local], max_entries)
    pair_j = np.empty(out_cap, dtype=np.int32)
    pair_lambda = np.empty(out_cap)
    slot = np.empty(2 * n_pair, dtype=np.int64)  # the entry each local side landed in
    n_hist = hist_offsets[n_local]
    far_e = np.empty(n_hist, dtype=np.int64)  # entries of inserted local history partners
    far_i = np.empty(n_hist, dtype=np.int64)
    n_far = 0
    pos = 0
    for i in range(n_local):
        s0 = row_start[i]
        cnt = row_start[i + 1] - s0
        # the row in gid order; two entries of one gid leave the build to ``_build_rows_sorted``
        for c in range(cnt):
            row_g[c] = cand_g[s0 + c]
            row_t[c] = cand_t[s0 + c]
        if cnt > _SORT_SHORT or not _rank_sort(row_g, row_t, cnt, work_g, work_t):
            _sort_row(row_g, row_t, cnt)
            for c in range(1, cnt):
                if row_g[c] == row_g[c - 1]:
                    return (pair_offsets, pair_j[:0].copy(), pair_lambda[:0].copy(), _FALL_BACK,
                            np.empty(0, dtype=np.int64))
        for c in range(cnt):
            row_j[c] = ends[row_t[c] ^ 1]
            row_l[c] = 0.0
        merged = _merge_history(i, cnt, row_g, row_j, row_l, row_t, hist_offsets, hist_gid, hist_lambda,
                                sgid, gorder, missing)
        if merged < 0:
            _gid_lookup(gid, n_total, sgid, gorder)
            missing[1] = 1
            merged = _merge_history(i, cnt, row_g, row_j, row_l, row_t, hist_offsets, hist_gid,
                                    hist_lambda, sgid, gorder, missing)
        cnt = merged
        if pos + cnt > max_entries:
            return (pair_offsets, pair_j[:0].copy(), pair_lambda[:0].copy(), -1,
                    np.empty(0, dtype=np.int64))
        for c in range(cnt):
            e = pos + c
            pair_j[e] = row_j[c]
            pair_lambda[e] = row_l[c]
            t = row_t[c]
            if t >= 0:
                slot[t] = e
            elif row_j[c] < n_local:
                far_e[n_far] = e
                far_i[n_far] = i
                n_far += 1
        pos += cnt
        pair_offsets[i + 1] = pos
    pair_j = pair_j[:pos].copy()
    mirror = np.full(pos, -1, dtype=np.int64)
    for k in range(n_pair):
        if ends[2 * k] < n_local and ends[2 * k + 1] < n_local:
            e0 = slot[2 * k]
            e1 = slot[2 * k + 1]
            mirror[e0] = e1
            mirror[e1] = e0
    # a far partner's entry is in the other's row only if its history holds the pair too
    for u in range(n_far):
        e = far_e[u]
        f = mirror_in_row(far_i[u], pair_j[e], gid, pair_offsets, pair_j)
        if f >= 0:
            mirror[e] = f
            mirror[f] = e
    return pair_offsets, pair_j, pair_lambda[:pos].copy(), missing[0], mirror


@njit(cache=True, inline="always")
def _build_rows_sorted(b, x, n_local, n_total, gid, diam, skin, hist_offsets, hist_gid, hist_lambda,
                       max_entries):
    """Pair rows of the local particles, one row at a time.

    x (n_total, b) with locals first; gid int64, diam float64 (n_total,);
    hist_offsets (n_local+1,), hist_gid int64, hist_lambda float64: local particle i's history
    is entries hist_offsets[i]:hist_offsets[i+1] (partner gid, lambda > 0).

    Returns (pair_offsets int64 (n_local+1,), pair_j int32 (n_pairs,), pair_lambda (n_pairs,),
    missing) where missing is the number of history partners not present in x (they must be
    made ghosts before the build; the caller treats missing > 0 as an error). If the rows would
    hold more than max_entries entries the build stops early and missing is -1: a start so
    dense that the rows would not fit in memory is reported, not attempted.

    A sphere's candidates are the 3^(b-1) runs of the cell order around its cell
    (``_cell_order``, ``_cell_runs``), read in place. Each row is assembled in buffers sized
    once for the longest possible row (3^b cells of the fullest occupancy, at most all
    particles, plus the longest history) and sorted by partner gid; history partners already
    among the candidates take their lambda, the others (far partners) are inserted. No buffer
    is reallocated inside the candidate loop: growable buffers there made the build 4x slower
    (measured: docs/research/convergence.md, section 3o).
    """
    pair_offsets = np.zeros(n_local + 1, dtype=np.int64)
    if n_local == 0:
        return pair_offsets, np.empty(0, dtype=np.int32), np.empty(0), 0
    keys, dims, dense, order, skeys, cell_start, xs, ds, gs = _cell_order(b, x, n_total, gid, diam, skin)
    offs = _stencil(b, False)
    row_g, row_j, row_l, row_t, row_g2, row_j2 = _row_buffers(
        n_total, 3 * offs.shape[0] * _max_occupancy(skeys), hist_offsets, n_local)
    # gid -> index lookup, filled only when a history partner is not among the candidates;
    # missing: (count, lookup filled)
    sgid = np.empty(n_total, dtype=np.int64)
    gorder = np.empty(n_total, dtype=np.int64)
    missing = np.zeros(2, dtype=np.int64)

    cap = min(max(16, n_local * 8), max(16, max_entries))
    pair_j = np.empty(cap, dtype=np.int32)
    pair_lambda = np.empty(cap)
    coord = np.empty(b, dtype=np.int64)
    # the runs of the cell order holding the candidates of the current cell
    run_start = np.empty(offs.shape[0], dtype=np.int64)
    run_end = np.empty(offs.shape[0], dtype=np.int64)
    n_runs = 0
    run_key = np.int64(-1)
    pos = 0
    for i in range(n_local):
        cnt = 0
        if keys[i] != run_key:
            run_key = keys[i]
            n_runs = _cell_runs(b, run_key, dims, dense, cell_start, skeys, offs, False, coord, run_start,
                                run_end)
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
        if cnt > _SORT_SHORT or not _rank_sort(row_g, row_j, cnt, row_g2, row_j2):
            _sort_row(row_g, row_j, cnt)
        for q in range(cnt):
            row_l[q] = 0.0
        merged = _merge_history(i, cnt, row_g, row_j, row_l, row_t, hist_offsets, hist_gid, hist_lambda,
                                sgid, gorder, missing)
        if merged < 0:
            _gid_lookup(gid, n_total, sgid, gorder)
            missing[1] = 1
            merged = _merge_history(i, cnt, row_g, row_j, row_l, row_t, hist_offsets, hist_gid,
                                    hist_lambda, sgid, gorder, missing)
        cnt = merged
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
    return pair_offsets, pair_j[:pos].copy(), pair_lambda[:pos].copy(), missing[0]


@njit(cache=True, inline="always")
def _build_rows(b, x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries):
    """``_build_rows_once``, or ``_build_rows_sorted`` where it falls back (mirror empty)."""
    if n_local > 0:
        out = _build_rows_once(b, x, n_local, n_total, gid, diam, skin, ho, hg, hl, max_entries)
        if out[3] != _FALL_BACK:
            return out
    offsets, pair_j, pair_lambda, missing = _build_rows_sorted(b, x, n_local, n_total, gid, diam, skin,
                                                               ho, hg, hl, max_entries)
    return offsets, pair_j, pair_lambda, missing, np.empty(0, dtype=np.int64)


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
    """Pair rows of the local particles (compiled per dimension; ``_build_rows_sorted`` says
    what they hold, ``_build_rows_once`` how they are usually found).

    Returns (pair_offsets int64 (n_local+1,), pair_j int32 (n_pairs,), pair_lambda (n_pairs,),
    missing, mirror); missing = -1 when the rows would exceed max_entries entries; mirror int64
    (n_pairs,) each entry's mirror (``_build_rows_once``), or None where the other build made
    the rows (a dense start's, or a gid twice among the particles; ``find_mirrors`` searches
    them).
    """
    f = (_build_rows_1, _build_rows_2, _build_rows_3)[x.shape[1] - 1]
    offsets, pair_j, pair_lambda, missing, mirror = f(
        x, n_local, n_total, gid, diam, skin, hist_offsets, hist_gid, hist_lambda, np.int64(max_entries))
    return offsets, pair_j, pair_lambda, missing, (mirror if mirror.shape[0] == pair_j.shape[0] and missing >= 0
                                                   else None)


# a row longer than this is searched by bisection on its partners' gids; a shorter one by a
# scan for the partner's index (no branch to mispredict, no gid read: about twice as fast in
# the rows of a packing, docs/benchmarks.md "Cheaper rebuilds")
_SCAN_ROW = 32


@njit(cache=True)
def mirror_in_row(i, j, gid, pair_offsets, pair_j):
    """The entry of local j's row whose partner is i, or -1 (rows in partner-gid order, a
    partner at most once a row): a scan of a short row, bisection on gids in a long one."""
    lo = pair_offsets[j]
    hi = pair_offsets[j + 1]
    if hi - lo <= _SCAN_ROW:
        f = -1
        for q in range(lo, hi):
            if pair_j[q] == i:
                f = q
        return f
    gi = gid[i]
    while lo < hi:
        mid = (lo + hi) // 2
        if gid[pair_j[mid]] < gi:
            lo = mid + 1
        else:
            hi = mid
    return lo if lo < pair_offsets[j + 1] and pair_j[lo] == i else -1


@njit(cache=True)
def find_mirrors(n_local, gid, pair_offsets, pair_j):
    """Each entry's mirror, searched (``mirror_in_row``): the entry of the partner's row whose
    partner is this entry's particle, or -1 (a ghost partner, or none). int64 (n_pairs,); what
    ``_build_rows_once`` gives with the rows."""
    mirror = np.full(pair_offsets[n_local], -1, dtype=np.int64)
    for i in range(n_local):
        for e in range(pair_offsets[i], pair_offsets[i + 1]):
            j = pair_j[e]
            if j >= n_local or j < i:
                continue
            f = mirror_in_row(i, j, gid, pair_offsets, pair_j)
            if f >= 0:
                mirror[e] = f
                mirror[f] = e
    return mirror


# a row of at most this many entries is sorted by ranks (``_rank_sort``), a longer one by
# ``_sort_row``
_SORT_SHORT = 48


@njit(cache=True, inline="always")
def _rank_sort(g, j, n, g_work, j_work):
    """Sort g[:n] ascending, permuting j alike, each entry placed at its rank (the number of
    smaller keys: n^2 comparisons with no branch, quicker than an insertion sort's mispredicted
    exits for a row of ~4-14 entries, docs/benchmarks.md "Cheaper rebuilds") in g_work, j_work,
    then copied back. Returns False, with g and j unchanged, if two keys are equal (their ranks
    are then not all distinct: the ranks' sum falls short of 0 + 1 + ... + n-1)."""
    rank_sum = 0
    for a in range(n):
        ga = g[a]
        r = 0
        for c in range(n):
            r += np.int64(g[c] < ga)
        g_work[r] = ga
        j_work[r] = j[a]
        rank_sum += r
    if rank_sum != n * (n - 1) // 2:
        return False
    for a in range(n):
        g[a] = g_work[a]
        j[a] = j_work[a]
    return True


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
def _gid_lookup(gid, n_total, sgid, gorder):
    """gorder[:n_total] = the indices that sort gid[:n_total], sgid their gids, in place."""
    o = np.argsort(gid[:n_total])
    for q in range(n_total):
        gorder[q] = o[q]
        sgid[q] = gid[o[q]]


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
