"""Spheres by space for post-processing: each rank owns a slab of the packing along the first
axis and holds, after its own rows, a halo of the other ranks' spheres within ``width`` of
the slab, so that every neighbour query about an owned sphere is answered locally. No physics.

    local = distribute(comm, gid, x, diam, width, fields)
    local.n_own, local.gid (n_own + n_halo,), local.x, local.diam, local.fields (owned rows)
    local.refresh(values)   # a per-sphere value of the owned rows -> its values on the halo rows

The slab cuts come from a global histogram of the first coordinate (equal counts per rank), so
the split depends on the rank count but no result does: a sphere's neighbourhood is complete
whichever rank owns it, per-sphere values are summed over partners in gid order, and global
sums are exact (``exact_total``) or integer. One rank holds everything and sends nothing.
"""

import numpy as np

from mpipack.parallel import exactsum

HISTOGRAM_BINS = 4096


class Local:
    """Owned rows first (gid order), then halo rows (see the module docstring)."""

    def __init__(self, comm, gid, x, diam, fields, n_own, send, recv_counts, input_dest):
        self.comm = comm
        self.gid, self.x, self.diam, self.fields = gid, x, diam, fields
        self.n_own = n_own
        self._send = send              # per rank: owned row indices sent as its halo
        # the rank each halo row came from (its owner), and where each input row went
        self.halo_source = np.repeat(np.arange(len(recv_counts)), recv_counts)
        self.input_dest = input_dest
        self._order = None

    def rows_of(self, gids):
        """Row indices of these gids among this rank's rows (owned and halo); -1 where absent."""
        gids = np.asarray(gids, dtype=np.int64)
        if len(self.gid) == 0:
            return np.full(len(gids), -1, np.int64)
        if self._order is None:
            self._order = np.argsort(self.gid, kind="stable")
        sorted_gid = self.gid[self._order]
        k = np.minimum(np.searchsorted(sorted_gid, gids), len(sorted_gid) - 1)
        return np.where(sorted_gid[k] == gids, self._order[k], -1)

    def refresh(self, values):
        """values: (n_own, ...) of the owned rows -> (n_halo, ...) for the halo rows, in halo
        row order (collective)."""
        values = np.ascontiguousarray(values)
        if self.comm.size == 1:
            return values[:0].copy()
        order = np.concatenate(self._send) if self._send else np.empty(0, np.int64)
        counts = np.array([len(s) for s in self._send], dtype=np.int64)
        got, _ = self.comm.alltoallv({"v": values[order]}, {"v": counts})
        return got["v"]

    def with_halo(self, values):
        """values of the owned rows followed by those of the halo rows."""
        return np.concatenate([values, self.refresh(values)])


def _cuts(comm, x0, n):
    """P - 1 cut values of the first coordinate with about n / P spheres between them."""
    P = comm.size
    lo = comm.allreduce(np.array([x0.min() if len(x0) else np.inf]), "min")[0]
    hi = comm.allreduce(np.array([x0.max() if len(x0) else -np.inf]), "max")[0]
    if not hi > lo:
        return np.full(P - 1, lo)
    edges = np.linspace(lo, hi, HISTOGRAM_BINS + 1)
    counts = comm.allreduce(np.histogram(x0, bins=edges)[0].astype(np.int64))
    cum = np.cumsum(counts)
    return np.array([edges[min(np.searchsorted(cum, n * k / P) + 1, HISTOGRAM_BINS)] for k in range(1, P)])


def distribute(comm, gid, x, diam, width, fields=None):
    """A ``Local`` from rows held in any way (e.g. gid blocks as read from a file): the rows
    move to the rank of their slab, and each rank receives the halo of its slab (collective).

    gid (m,) int64, x (m, b), diam (m,), fields {name: (m, ...)}: per-sphere values carried
    with the owned rows; width: the halo width (a distance)."""
    fields = dict(fields or {})
    if comm.size == 1:
        order = np.argsort(gid, kind="stable")
        return Local(comm, gid[order], x[order], diam[order], {k: v[order] for k, v in fields.items()},
                     len(gid), [], np.zeros(1, np.int64), np.zeros(len(gid), np.int64))
    P, n = comm.size, int(comm.allreduce(np.array([len(gid)], np.int64))[0])
    cuts = _cuts(comm, x[:, 0], n)
    owner = np.searchsorted(cuts, x[:, 0], side="right")
    order = np.argsort(owner, kind="stable")
    counts = np.bincount(owner, minlength=P).astype(np.int64)
    rows = {"gid": gid[order], "x": x[order], "diam": diam[order],
            **{"f_" + k: v[order] for k, v in fields.items()}}
    got, _ = comm.alltoallv(rows, {k: counts for k in rows})
    mine = np.argsort(got["gid"], kind="stable")
    gid, x, diam = got["gid"][mine], got["x"][mine], got["diam"][mine]
    fields = {k: got["f_" + k][mine] for k in fields}
    # the halo: my rows within width of each other rank's slab [cut_{r-1}, cut_r)
    bounds = np.concatenate(([-np.inf], cuts, [np.inf]))
    send = []
    for r in range(P):
        if r == comm.rank:
            send.append(np.empty(0, np.int64))
            continue
        near = (x[:, 0] >= bounds[r] - width) & (x[:, 0] < bounds[r + 1] + width)
        send.append(np.flatnonzero(near).astype(np.int64))
    idx = np.concatenate(send)
    hcounts = np.array([len(s) for s in send], dtype=np.int64)
    halo, recv = comm.alltoallv({"gid": gid[idx], "x": x[idx], "diam": diam[idx]},
                                {"gid": hcounts, "x": hcounts, "diam": hcounts})
    return Local(comm, np.concatenate([gid, halo["gid"]]), np.concatenate([x, halo["x"]]),
                 np.concatenate([diam, halo["diam"]]), fields, len(gid), send, recv["gid"], owner)


def route_pairs(comm, local, first_gid, gi, gj, values):
    """Pairs given by the rank that read gid_i (gids [first_gid, ...) of the input rows, as
    ``distribute`` got them) -> the directed pairs (i, j, value) of this rank, i an owned row and
    j any row, both directions of each pair, sorted by (gid_i, gid_j). Raises ValueError when a
    partner is not among this rank's rows (a pair longer than the halo width)."""
    if comm.size == 1:
        a, b = local.rows_of(gi), local.rows_of(gj)
        if np.any(a < 0) or np.any(b < 0):
            raise ValueError("a pair names a sphere the file does not hold")
        i, j, v = np.concatenate([a, b]), np.concatenate([b, a]), np.concatenate([values, values])
    else:
        dest = local.input_dest[gi - first_gid]
        fi, fj, fv = _send_pairs(comm, local, dest, gi, gj, values)   # i owned here
        # the reverse direction: here when j is owned here too, else to the rank j's halo
        # copy came from (its owner)
        mine = fj < local.n_own
        back = local.halo_source[fj[~mine] - local.n_own]
        ri, rj, rv = _send_pairs(comm, local, back, local.gid[fj[~mine]], local.gid[fi[~mine]], fv[~mine])
        i = np.concatenate([fi, fj[mine], ri])
        j = np.concatenate([fj, fi[mine], rj])
        v = np.concatenate([fv, fv[mine], rv])
    order = np.lexsort((local.gid[j], local.gid[i]))
    return i[order], j[order], v[order]


def _send_pairs(comm, local, dest, gi, gj, values):
    order = np.argsort(dest, kind="stable")
    counts = np.bincount(dest, minlength=comm.size).astype(np.int64)
    got, _ = comm.alltoallv({"gi": gi[order], "gj": gj[order], "v": values[order]},
                            {"gi": counts, "gj": counts, "v": counts})
    a, b = local.rows_of(got["gi"]), local.rows_of(got["gj"])
    bad = (a < 0) | (a >= local.n_own) | (b < 0)
    if comm.allreduce(np.array([bad.sum()], np.int64))[0]:
        raise ValueError("a contact pair is longer than the halo width")
    return a, b, got["v"]


def exact_total(comm, values):
    """The sum of ``values`` over every rank, independent of their order and of the rank count
    (exact integer accumulators, ``parallel.exactsum``); NaN if a value is not finite."""
    acc = exactsum.new_accumulator(1)
    exactsum.accumulate(np.ascontiguousarray(values, dtype=np.float64).ravel(), acc, 0)
    return float(exactsum.value(comm.allreduce(acc), 0))


def exact_totals(comm, columns):
    """``exact_total`` of several arrays in one reduction: a list of floats."""
    acc = exactsum.new_accumulator(len(columns))
    for q, v in enumerate(columns):
        exactsum.accumulate(np.ascontiguousarray(v, dtype=np.float64).ravel(), acc, q)
    acc = comm.allreduce(acc)
    return [float(exactsum.value(acc, q)) for q in range(len(columns))]


def total(comm, values):
    """Element-wise sum over ranks of an integer array (histograms, counts): exact."""
    return comm.allreduce(np.ascontiguousarray(values, dtype=np.int64))


def gather_rows(comm, arrays, root=0):
    """{name: (m, ...)} of every rank concatenated on ``root`` in rank order (None elsewhere)."""
    if comm.size == 1:
        return {k: np.asarray(v) for k, v in arrays.items()}
    parts = comm.mpi.gather({k: np.asarray(v) for k, v in arrays.items()}, root=root)
    if comm.rank != root:
        return None
    return {k: np.concatenate([p[k] for p in parts]) for k in arrays}
