"""Inter-rank communication: moving particle data and reduced numbers. No physics here.

The verbs (as in LAMMPS' comm_brick), each a function of this module:

    exchange      migrate particles, with their pair history, to the rank that owns their position
    borders       send copies of particles near another rank's box (that rank's ghosts), plus
                  any pair-history partner further away (requested from its owner by gid)
    forward       refresh ghost positions from their owners (every iteration)
    reduce_fused  one allreduce of exact sums, integer counts and maxima (every iteration)
    to_gid_blocks redistribute particles to the owners of consecutive gid blocks (state out)
    gather_by_gid everything on one rank, in gid order (tests and small N)

Counting (``Comm.count()``, off unless asked for): what this rank sends, by category, in a
``Counts``: point-to-point messages and their bytes, collective calls and the bytes this rank
puts in. The verbs charge their own category (``forward``, ``reduce``, ``exchange``,
``borders``, ``far``); the plain collectives (``allreduce``, ``allgather_object``, ...) charge
the category in force (``charged_to``: the solver's rebuild charges ``rebuild``, else
``other``). Off, a verb pays one attribute test; counting never changes what is sent.

Particles travel as a dict of per-particle arrays (``part``: local rows, any names) plus their
pair history as CSR (``hist`` = (offsets (n+1,), partner gid, lambda)): the layout of
``state.State.local_fields`` and ``neighbors.history``. A run on one rank never calls MPI in
the loop: every verb has a size-1 short cut (the solver does not even call exchange and borders).
"""

import numba
import numpy as np
from mpi4py import MPI

from mpipack.jit import cfunc, njit
from mpipack.parallel import neighbors
from mpipack.parallel.state import gather_rows

# point-to-point tags: the ghost refresh (7), alltoallv's counts (two, alternating) and data
_COUNTS_TAG = 100
_DATA_TAG = 200
_ALLTOALLV_CALLS = {}  # MPI communicator handle -> alltoallv calls so far (the counts' tag parity)
_FUSED_OP = None
_FUSED_OP_KIND = None  # "compiled" or "python" once made

# the kinds of traffic a Counts row holds: point-to-point messages, or one kind of collective
P2P, ALLREDUCE, ALLTOALL, ALLGATHER, BCAST, GATHER, BARRIER = (
    "p2p", "allreduce", "alltoall", "allgather", "bcast", "gather", "barrier")


class Counts:
    """What one rank sent, by category and kind: ``rows[category][kind] = [n, bytes]``.

    kind ``p2p``: n messages this rank sent (one per destination rank and buffer; an empty
    buffer is not sent) and their payload bytes. A collective kind (``allreduce``,
    ``alltoall``, ``allgather``, ``bcast``, ``gather``, ``barrier``): n calls and the bytes of
    this rank's send buffer (a pickled object counts its numpy payload, not the pickle). How
    many messages a collective becomes is the MPI library's algorithm; a model of it is the
    reader's (``experiments.scaling``). Self-sends are not counted.
    """

    def __init__(self):
        self.rows = {}
        self.category = "other"  # where the plain collectives are charged (``Comm.charged_to``)

    def add(self, category, kind, n, nbytes):
        kinds = self.rows.get(category)
        if kinds is None:
            kinds = self.rows[category] = {}
        row = kinds.get(kind)
        if row is None:
            row = kinds[kind] = [0, 0]
        row[0] += n
        row[1] += nbytes

    def snapshot(self):
        """A copy of the rows: {category: {kind: (n, bytes)}}."""
        return {c: {k: (v[0], v[1]) for k, v in kinds.items()} for c, kinds in self.rows.items()}

    @staticmethod
    def difference(after, before):
        """after - before, two snapshots; rows that did not change are left out."""
        out = {}
        for c, kinds in after.items():
            for k, (n, b) in kinds.items():
                n0, b0 = before.get(c, {}).get(k, (0, 0))
                if n != n0 or b != b0:
                    out.setdefault(c, {})[k] = (n - n0, b - b0)
        return out


class _Charge:
    """Context of ``Comm.charged_to``: the plain collectives inside charge ``category``."""

    def __init__(self, counts, category):
        self.counts, self.category, self.before = counts, category, None

    def __enter__(self):
        if self.counts is not None:
            self.before, self.counts.category = self.counts.category, self.category
        return self

    def __exit__(self, *exc):
        if self.counts is not None:
            self.counts.category = self.before
        return False


def _payload_bytes(obj):
    """Bytes of the numpy arrays in an object sent pickled (lists, tuples and dicts walked)."""
    if isinstance(obj, np.ndarray):
        return obj.nbytes
    if isinstance(obj, (list, tuple)):
        return sum(_payload_bytes(v) for v in obj)
    if isinstance(obj, dict):
        return sum(_payload_bytes(v) for v in obj.values())
    return 8


# ---- the fused reduction's op ---------------------------------------------------------------
# Buffer layout: buf[0] = n_sum, buf[1] = n_max (the same on every rank), then n_sum int64 summed,
# then n_max maxima: non-negative float64 as their int64 bit patterns, whose order is the
# floats' order (NaN mapped to INT64_MAX so that it wins).
_INT64_MAX = np.iinfo(np.int64).max


@njit(cache=True, nogil=True)
def _combine(a, b):
    """b <- a (+) b for one or more whole fused buffers laid end to end (int64 arrays)."""
    start = 0
    while start < b.size:
        n_sum, n_max = b[start], b[start + 1]
        first_max = start + 2 + n_sum
        for i in range(start + 2, first_max):
            b[i] += a[i]
        for i in range(first_max, first_max + n_max):
            if a[i] > b[i]:
                b[i] = a[i]
        start = first_max + n_max


@cfunc(numba.types.void(numba.types.voidptr, numba.types.voidptr,
                        numba.types.CPointer(numba.types.intc), numba.types.voidptr),
       cache=True)
def _fused_op_c(inbuf, inoutbuf, count, datatype):
    """MPI_User_function: ``count`` elements of the whole-buffer datatype. Their length is read
    from the header of each (the datatype is not asked: no MPI call from inside the op)."""
    head = numba.carray(inoutbuf, 2, np.int64)
    n = 2 + head[0] + head[1]  # every element of one call has the same layout
    total = n * count[0]
    _combine(numba.carray(inbuf, total, np.int64), numba.carray(inoutbuf, total, np.int64))


def _fused_op_fn(inbuf, outbuf, datatype):
    """The same combine as a Python op (mpi4py calls it with buffers): used where the compiled
    op cannot be registered with the MPI library, and as its reference in the tests."""
    _combine(np.frombuffer(inbuf, dtype=np.int64), np.frombuffer(outbuf, dtype=np.int64))


def _compiled_op():
    """Register ``_fused_op_c`` with the MPI library (MPI_Op_create through ctypes) and wrap its
    handle; None when the library's symbol cannot be found. mpi4py's own ``Op.Create`` calls a
    Python function at every combine, several times the cost of a built-in op
    (docs/benchmarks.md, session 31)."""
    import ctypes
    import ctypes.util
    create = None
    for name in (None, ctypes.util.find_library("mpi")):
        try:
            create = ctypes.CDLL(name, mode=ctypes.RTLD_GLOBAL).MPI_Op_create
            break
        except (OSError, AttributeError):
            continue
    if create is None:
        return None
    handle_type = {8: ctypes.c_void_p, 4: ctypes.c_int}.get(MPI._sizeof(MPI.Op))
    if handle_type is None:
        return None
    handle = handle_type()
    create.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_void_p]
    create.restype = ctypes.c_int
    if create(_fused_op_c.address, 1, ctypes.byref(handle)) != 0:
        return None
    return MPI.Op.fromhandle(handle.value)


def _fused_op():
    global _FUSED_OP, _FUSED_OP_KIND
    if _FUSED_OP is None:
        _FUSED_OP, _FUSED_OP_KIND = _compiled_op(), "compiled"
        if _FUSED_OP is None:
            _FUSED_OP, _FUSED_OP_KIND = MPI.Op.Create(_fused_op_fn, commute=True), "python"
    return _FUSED_OP


@njit(cache=True)
def _pack(sums, maxima, buf):
    """buf <- [n_sum, n_max, sums, maxima as ordered int64 bits (NaN: INT64_MAX)]."""
    n_sum = sums.size
    buf[0] = n_sum
    buf[1] = maxima.size
    buf[2:2 + n_sum] = sums
    bits = maxima.view(np.int64)
    for j in range(maxima.size):
        buf[2 + n_sum + j] = _INT64_MAX if np.isnan(maxima[j]) else bits[j]


@njit(cache=True)
def _unpack_maxima(buf, n_sum):
    """The float64 maxima of a reduced buffer (INT64_MAX back to NaN), a new array."""
    bits = buf[2 + n_sum:].copy()
    out = bits.view(np.float64)
    for j in range(bits.size):
        if bits[j] == _INT64_MAX:
            out[j] = np.nan
    return out


_FUSED_TYPES = {}


def _fused_type(n):
    """The whole fused buffer of n int64 as ONE element of a contiguous datatype: the op reads
    its layout from buf[0:2], so MPI must never hand it a piece of the buffer. With n int64 of
    count n, Open MPI's segmented algorithms (ring, reduce-scatter + allgather: 8 ranks and a
    buffer of 5000, 2 ranks and 1000, 32 ranks and the loop's 32) call the op on slices."""
    t = _FUSED_TYPES.get(n)
    if t is None:
        t = _FUSED_TYPES[n] = MPI.INT64_T.Create_contiguous(n).Commit()
    return t


class Comm:
    """A communicator plus the verbs above. ``rank`` and ``size`` as in MPI."""

    def __init__(self, mpi_comm=None):
        self.mpi = mpi_comm if mpi_comm is not None else MPI.COMM_WORLD
        self.rank = self.mpi.Get_rank()
        self.size = self.mpi.Get_size()
        if self.size == 1:
            self.ranks_per_node = 1
        else:
            node = self.mpi.Split_type(MPI.COMM_TYPE_SHARED)
            self.ranks_per_node = node.Get_size()
            node.Free()
        self.counts = None  # a Counts while counting (``count``)

    def count(self, on=True):
        """Start counting this rank's traffic afresh (``on``) or stop; returns the Counts
        (or None). Counting is local: no rank needs to agree."""
        self.counts = Counts() if on else None
        return self.counts

    def charged_to(self, category):
        """``with comm.charged_to("rebuild"):`` the plain collectives inside count as ``category``."""
        return _Charge(self.counts, category)

    def _charge(self, kind, nbytes, category=None):
        c = self.counts
        c.add(category or c.category, kind, 1, nbytes)

    @classmethod
    def serial(cls):
        """This process alone (MPI.COMM_SELF), whatever the launcher started."""
        return cls(MPI.COMM_SELF)

    # ---- reductions ------------------------------------------------------------------------
    def reduce_fused(self, sums, maxima):
        """One allreduce: element-wise integer sum of ``sums`` and max of ``maxima``.

        sums: int64 array (any shape, summed exactly); maxima: float64 array of values >= 0
        (or NaN, which wins). Returns (global_sums, global_maxima), new arrays.
        """
        sums = np.ascontiguousarray(sums, dtype=np.int64)
        maxima = np.ascontiguousarray(maxima, dtype=np.float64)
        if self.size == 1:
            return sums.copy(), maxima.copy()
        n_sum = sums.size
        buf = np.empty(2 + n_sum + maxima.size, dtype=np.int64)
        _pack(sums.reshape(-1), maxima.reshape(-1), buf)
        out = np.empty_like(buf)
        if self.counts is not None:
            self.counts.add("reduce", ALLREDUCE, 1, buf.nbytes)
        whole = _fused_type(buf.size)
        self.mpi.Allreduce([buf, 1, whole], [out, 1, whole], op=_fused_op())
        g_sums = out[2:2 + n_sum].reshape(sums.shape)
        g_max = _unpack_maxima(out, n_sum).reshape(maxima.shape)
        return g_sums, g_max

    def allreduce(self, array, op="sum"):
        """Element-wise allreduce of a numpy array (sum, min or max); used off the hot path."""
        array = np.ascontiguousarray(array)
        if self.size == 1:
            return array.copy()
        out = np.empty_like(array)
        mop = {"sum": MPI.SUM, "min": MPI.MIN, "max": MPI.MAX}[op]
        if self.counts is not None:
            self._charge(ALLREDUCE, array.nbytes)
        self.mpi.Allreduce(array, out, op=mop)
        return out

    def allgather_object(self, obj, category=None):
        if self.size == 1:
            return [obj]
        if self.counts is not None:
            self._charge(ALLGATHER, _payload_bytes(obj), category)
        return self.mpi.allgather(obj)

    def bcast_object(self, obj, root=0):
        if self.size == 1:
            return obj
        if self.counts is not None:
            self._charge(BCAST, _payload_bytes(obj) if self.rank == root else 0)
        return self.mpi.bcast(obj, root=root)

    def barrier(self):
        if self.size > 1:
            if self.counts is not None:
                self._charge(BARRIER, 0)
            self.mpi.Barrier()

    def abort(self, code):
        self.mpi.Abort(code)

    # ---- particle movement -----------------------------------------------------------------
    def alltoallv(self, arrays, send_counts, category=None):
        """Send rows of each array to ranks: rows of ``arrays[name]`` are grouped by destination,
        ``send_counts[name][r]`` rows to rank r (name-specific counts allow ragged payloads).
        ``category``: what the traffic is charged to while counting (default: the one in force).

        Returns (received arrays, recv_counts per name), rows grouped by source rank in rank
        order. Sparse: a rank exchanges messages only with the ranks it sends rows to or gets
        rows from (its neighbours in the partition), never with all K - 1 others. Who sends
        to me is learnt by a non-blocking consensus (``_sparse_counts``: one synchronous send
        of the counts to each destination, then a non-blocking barrier: log2 K latencies, not
        the K - 1 of an Alltoall of counts); then one message per array and peer with rows.
        """
        names = list(arrays)
        counts = np.array([send_counts[n] for n in names], dtype=np.int64).T.copy()  # (P, n)
        if self.counts is not None:
            self._count_alltoallv(arrays, counts, category or self.counts.category)
        recv = self._sparse_counts(counts)
        me = self.rank
        srcs, dsts = _other_ranks_with_rows(recv, me), _other_ranks_with_rows(counts, me)
        out, out_counts, reqs, sent = {}, {}, [], []
        for q, name in enumerate(names):
            a = np.ascontiguousarray(arrays[name])
            sent.append(a)  # alive until the sends complete
            s_off = np.concatenate(([0], np.cumsum(counts[:, q])))
            r_off = np.concatenate(([0], np.cumsum(recv[:, q])))
            r = np.empty((int(r_off[-1]),) + a.shape[1:], dtype=a.dtype)
            r[r_off[me]:r_off[me + 1]] = a[s_off[me]:s_off[me + 1]]
            tag = _DATA_TAG + q
            reqs += [self.mpi.Irecv(r[r_off[s]:r_off[s + 1]], source=s, tag=tag) for s in srcs if recv[s, q]]
            reqs += [self.mpi.Isend(a[s_off[d]:s_off[d + 1]], dest=d, tag=tag) for d in dsts if counts[d, q]]
            out[name] = r
            out_counts[name] = recv[:, q].copy()
        MPI.Request.Waitall(reqs)
        return out, out_counts

    def _sparse_counts(self, counts):
        """recv (P, n): recv[s] = rank s's counts row for this rank, from the ranks that have
        rows for it; zero elsewhere. counts (P, n): this rank's rows for each rank.

        NBX (Hoefler, Siebert and Lumsdaine 2010): a synchronous send of counts[d] to each rank
        d with rows; receive whatever arrives while probing; once every send of this rank is
        matched, enter a non-blocking barrier; done when the barrier completes (every rank's
        sends are then matched, so nothing is still on its way). The tag alternates between
        calls on one MPI communicator: a rank one call ahead (it cannot be two: the barrier
        waits for this one) is not taken for this call's sender.
        """
        me = self.rank
        recv = np.zeros_like(counts)
        recv[me] = counts[me]
        if self.size == 1:
            return recv
        handle = self.mpi.py2f()  # calls are counted per MPI communicator, whatever Comm wraps it
        calls = _ALLTOALLV_CALLS.get(handle, 0)
        _ALLTOALLV_CALLS[handle] = calls + 1
        tag = _COUNTS_TAG + (calls & 1)
        sends = [self.mpi.Issend(counts[d], dest=d, tag=tag) for d in _other_ranks_with_rows(counts, me)]
        status = MPI.Status()
        barrier = None
        while True:
            if self.mpi.Iprobe(source=MPI.ANY_SOURCE, tag=tag, status=status):
                src = status.Get_source()
                self.mpi.Recv(recv[src], source=src, tag=tag)
            elif barrier is None:
                if MPI.Request.Testall(sends):
                    barrier = self.mpi.Ibarrier()
            elif barrier.Test():
                return recv

    def _count_alltoallv(self, arrays, counts, category):
        """Charge an ``alltoallv``: the counts' consensus (one point-to-point message per rank
        this rank has rows for, and one non-blocking barrier), then each array's rows to each
        other rank."""
        c, me = self.counts, self.rank
        peers = _other_ranks_with_rows(counts, me)
        c.add(category, P2P, len(peers), len(peers) * counts.shape[1] * counts.itemsize)
        c.add(category, BARRIER, 1, 0)
        for q, name in enumerate(arrays):
            a = arrays[name]
            row_bytes = a.itemsize * (int(np.prod(a.shape[1:])) if a.ndim > 1 else 1)
            rows = counts[:, q]
            peers = int(np.count_nonzero(rows)) - (1 if rows[me] > 0 else 0)
            c.add(category, P2P, peers, (int(rows.sum()) - int(rows[me])) * row_bytes)


def _other_ranks_with_rows(counts, me):
    """The ranks r != me whose row of counts (P, n: rows per rank and array) is not all zero,
    in rank order: the peers an ``alltoallv`` exchanges messages with."""
    return [r for r in np.flatnonzero(counts.any(axis=1)).tolist() if r != me]


class GhostPlan:
    """Who sends which local rows to whom, and where received ghosts go.

    send_ranks[m] gets local rows send_idx[send_offsets[m]:send_offsets[m+1]];
    recv_ranks[m]'s rows land at ghost rows recv_offsets[m]:recv_offsets[m+1]
    (counted from the first ghost row, i.e. x[n_local + recv_offsets[m]]).
    """

    def __init__(self, send_ranks, send_offsets, send_idx, recv_ranks, recv_offsets):
        self.send_ranks = send_ranks
        self.send_offsets = send_offsets
        self.send_idx = send_idx
        self.recv_ranks = recv_ranks
        self.recv_offsets = recv_offsets
        self._sendbuf = None

    @staticmethod
    def empty():
        z = np.zeros(1, dtype=np.int64)
        return GhostPlan([], z, np.empty(0, dtype=np.int64), [], z)


def _send_copies(comm, dest_offsets, dest_idx, fields, category="borders"):
    """Send copies of local rows to other ranks: one round of the ghost exchange.

    dest_offsets (P+1,), dest_idx: rank r gets local rows dest_idx[dest_offsets[r]:...];
    fields: dict name -> per-particle array of local rows (e.g. x, gid, diam).
    Returns (GhostPlan, dict of received ghost arrays in plan order).
    """
    P = comm.size
    counts = np.diff(dest_offsets)
    arrays = {k: np.ascontiguousarray(v[dest_idx]) for k, v in fields.items()}
    got, rcounts = comm.alltoallv(arrays, {k: counts for k in fields}, category)
    rc = rcounts[next(iter(fields))]
    send_ranks = [r for r in range(P) if counts[r] > 0]
    send_offsets = np.concatenate(([0], np.cumsum([counts[r] for r in send_ranks]))).astype(np.int64)
    recv_ranks = [r for r in range(P) if rc[r] > 0]
    recv_offsets = np.concatenate(([0], np.cumsum([rc[r] for r in recv_ranks]))).astype(np.int64)
    plan = GhostPlan(send_ranks, send_offsets, np.ascontiguousarray(dest_idx, dtype=np.int64),
                     recv_ranks, recv_offsets)
    return plan, got


def forward(comm, plan, x, n_local):
    """Refresh ghost rows x[n_local:] from their owners' local rows (nonblocking point-to-point).

    Also used for any other per-particle array laid out like x (e.g. NAP/NAV's X^p)."""
    if comm.size == 1 or (not plan.send_ranks and not plan.recv_ranks):
        return
    b = x.shape[1]
    n_send = plan.send_idx.shape[0]
    if plan._sendbuf is None or plan._sendbuf.shape != (n_send, b):
        plan._sendbuf = np.empty((n_send, b))
    np.take(x, plan.send_idx, axis=0, out=plan._sendbuf)
    if comm.counts is not None:
        comm.counts.add("forward", P2P, len(plan.send_ranks), plan._sendbuf.nbytes)
    reqs = []
    for m, r in enumerate(plan.recv_ranks):
        lo = n_local + plan.recv_offsets[m]
        hi = n_local + plan.recv_offsets[m + 1]
        reqs.append(comm.mpi.Irecv(x[lo:hi], source=r, tag=7))
    for m, r in enumerate(plan.send_ranks):
        reqs.append(comm.mpi.Isend(plan._sendbuf[plan.send_offsets[m]:plan.send_offsets[m + 1]], dest=r, tag=7))
    MPI.Request.Waitall(reqs)


def exchange(comm, owners, part, hist):
    """Migrate: every particle goes to rank ``owners[i]``; its pair history goes with it.

    owners (n,) int64 from the partition; part: dict of per-particle arrays (n rows);
    hist: (offsets (n+1,), partner gid, lambda). Returns the new (part, hist): the particles
    that stayed first (in their order), then the arrivals grouped by source rank.
    """
    hist_off, hist_gid, hist_lam = hist
    order = np.argsort(owners, kind="stable")
    movers = order[owners[order] != comm.rank]
    stay = np.flatnonzero(owners == comm.rank)
    dest = owners[movers]
    counts = np.bincount(dest, minlength=comm.size).astype(np.int64)
    h_off, h_idx = gather_rows(hist_off, movers)
    h_counts = np.diff(h_off)
    h_per_rank = np.bincount(dest, weights=h_counts, minlength=comm.size).astype(np.int64)
    send = {k: v[movers] for k, v in part.items()}
    send.update({"h_count": h_counts, "h_gid": hist_gid[h_idx], "h_lam": hist_lam[h_idx]})
    send_counts = {k: counts for k in part}
    send_counts.update({"h_count": counts, "h_gid": h_per_rank, "h_lam": h_per_rank})
    got, _ = comm.alltoallv(send, send_counts, "exchange")
    s_off, s_idx = gather_rows(hist_off, stay)
    counts_all = np.concatenate([np.diff(s_off), got["h_count"]])
    new_off = np.zeros(counts_all.shape[0] + 1, dtype=np.int64)
    np.cumsum(counts_all, out=new_off[1:])
    new_part = {k: np.concatenate([v[stay], got[k]]) for k, v in part.items()}
    return new_part, (new_off, np.concatenate([hist_gid[s_idx], got["h_gid"]]),
                      np.concatenate([hist_lam[s_idx], got["h_lam"]]))


def borders(comm, dest_offsets, dest_idx, fields, hist_gid):
    """Ghosts: send copies of local rows to the ranks that need them, then make sure every
    pair-history partner (lambda > 0) of a local particle is present, however far away.

    dest_offsets (P+1,), dest_idx: rank r gets local rows dest_idx[dest_offsets[r]:...]
    (from ``domain.ghost_destinations``); fields: dict name -> per-particle array of local
    rows, with at least "gid"; hist_gid: partner gids of the local particles' histories.
    A partner that is not among the locals and the ghosts received is requested from its
    owner by gid (one allgather of the requests) and the send lists are redone with it.
    Returns (GhostPlan for ``forward``, dict of ghost arrays in plan order, number of far
    partners requested over all ranks).
    """
    plan, got = _send_copies(comm, dest_offsets, dest_idx, fields)
    gid = fields["gid"]
    n_local = gid.shape[0]
    present = np.concatenate([gid, got["gid"]])
    missing = neighbors.missing_partners(present, hist_gid)  # sorted, unique
    requests = comm.allgather_object(missing, "far")
    n_far = int(sum(len(r) for r in requests))
    if n_far == 0:
        return plan, got, 0
    # far partners: each owner adds the requested particles to its send lists
    lookup = np.argsort(gid)
    sorted_gid = gid[lookup]
    ranks = [np.repeat(np.arange(comm.size), np.diff(dest_offsets))]
    rows = [dest_idx]
    for r, req in enumerate(requests):
        if r == comm.rank or len(req) == 0 or n_local == 0:
            continue
        pos = np.minimum(np.searchsorted(sorted_gid, req), n_local - 1)
        mine = lookup[pos[sorted_gid[pos] == req]]
        mine = np.setdiff1d(mine, dest_idx[dest_offsets[r]:dest_offsets[r + 1]])
        ranks.append(np.full(mine.shape[0], r, dtype=np.int64))
        rows.append(mine.astype(np.int64))
    ranks = np.concatenate(ranks)
    rows = np.concatenate(rows)
    o = np.argsort(ranks, kind="stable")
    offsets = np.zeros(comm.size + 1, dtype=np.int64)
    np.cumsum(np.bincount(ranks, minlength=comm.size), out=offsets[1:])
    # the ghosts are sent again with the far partners among them: charged to "far"
    plan, got = _send_copies(comm, offsets, rows[o], fields, "far")
    return plan, got, n_far


def to_gid_blocks(comm, n_global, part, hist):
    """Redistribute particles so that rank r holds gids [N r/P, N (r+1)/P), in gid order.

    part: dict of per-particle arrays with "gid"; hist: (offsets, partner gid, lambda).
    Returns (part, hist) of this rank's block, rows sorted by gid: the partition-free form of
    the state (``state.BlockState``).
    """
    P = comm.size
    gid = part["gid"]
    # the block of gid g is the r with N r/P <= g < N (r+1)/P (empty blocks when N < P)
    bounds = (np.arange(P + 1, dtype=np.int64) * n_global) // P
    owners = (np.searchsorted(bounds, gid, side="right") - 1).astype(np.int64)
    if P > 1:
        part, hist = exchange(comm, owners, part, hist)
    o = np.argsort(part["gid"], kind="stable")
    part = {k: v[o] for k, v in part.items()}
    h_off, h_idx = gather_rows(hist[0], o)
    return part, (h_off, hist[1][h_idx], hist[2][h_idx])


def gather_by_gid(comm, arrays, root=0):
    """Concatenate the ranks' per-particle arrays on ``root`` and sort by arrays["gid"].

    Returns the dict on root, None elsewhere. Arrays without a "gid" row alignment (ragged
    data such as pair lists) are passed as ``arrays["_ragged"]``: a dict concatenated as is.
    """
    ragged = arrays.pop("_ragged", {})
    mine = (arrays, ragged)
    if comm.size > 1 and comm.counts is not None:
        comm._charge(GATHER, _payload_bytes(mine))
    parts = [mine] if comm.size == 1 else comm.mpi.gather(mine, root=root)
    if comm.rank != root:
        return None
    cat = {k: np.concatenate([p[0][k] for p in parts]) for k in arrays}
    o = np.argsort(cat["gid"], kind="stable")
    out = {k: v[o] for k, v in cat.items()}
    out["_ragged"] = {k: np.concatenate([p[1][k] for p in parts]) for k in ragged}
    return out
