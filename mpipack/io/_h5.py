"""Shared HDF5 and MPI plumbing for the io modules. No physics, no file formats.

h5py is imported lazily (``h5py()``): a run that writes no HDF5 never imports it. Every
collective HDF5 call goes through the low-level API here rather than h5py's ``dset[...] = ...``,
because h5py skips the H5Dwrite call when a rank's selection is empty, and a rank that skips a
collective write hangs the others.
"""

import json
import os

import numpy as np

_H5PY = None


def h5py():
    """The h5py module, imported on first use."""
    global _H5PY
    if _H5PY is None:
        import h5py as _mod
        _H5PY = _mod
    return _H5PY


def h5py_has_mpi():
    return bool(h5py().get_config().mpi)


def mpi():
    from mpi4py import MPI
    return MPI


# ---- collective decisions -------------------------------------------------------------------

def first_error(comm, message):
    """Every rank gets the message of the lowest rank that has one (or None): a decision taken
    the same way everywhere, so all ranks raise or none does."""
    if comm.size == 1:
        return message
    msgs = comm.mpi.allgather(message)
    for m in msgs:
        if m is not None:
            return m
    return None


def one_line(text):
    """A message on one line (HDF5's errors can span several)."""
    return " ".join(str(text).split())


_MASK64 = (1 << 64) - 1
_WEIGHT = np.uint64(0x9E3779B97F4A7C15)


def checksum_rows(rows, first_row):
    """This rank's share of a dataset's checksum, rows ``first_row ..`` of it: the sum of every
    element's 64 bits times an odd weight of its position in the whole dataset, mod 2^64. A sum
    over the ranks' shares (``checksum_total``) is the same whatever rows each rank holds, so a
    file written on P ranks is checked on any number; a changed, swapped or overwritten element
    changes it (unless another change cancels it exactly)."""
    a = np.ascontiguousarray(rows)
    return checksum_at(a, np.arange(first_row, first_row + len(a), dtype=np.int64))


def checksum_at(rows, row_index):
    """``checksum_rows`` of rows that sit at the (scattered) rows ``row_index`` of the dataset."""
    a = np.ascontiguousarray(rows)
    width = int(np.prod(a.shape[1:])) if a.ndim > 1 else 1
    bits = a.reshape(-1).view(np.uint64) if a.dtype.itemsize == 8 else \
        a.reshape(-1).astype(np.int64).view(np.uint64)
    index = (np.asarray(row_index, dtype=np.uint64)[:, None] * np.uint64(width)
             + np.arange(width, dtype=np.uint64)[None, :]).reshape(-1)
    with np.errstate(over="ignore"):
        weight = index * _WEIGHT + np.uint64(1)
        return int(np.sum(bits * weight, dtype=np.uint64))


def checksums_attr(checksums):
    """The JSON text an attribute stores {name: checksum} as (decimal strings: HDF5 attributes
    and JSON readers may not keep 64-bit integers)."""
    return json.dumps({k: str(v) for k, v in sorted(checksums.items())})


def checksums_from_attr(text):
    """{name: int} of a ``checksums_attr`` text; None when it cannot be read."""
    try:
        return {k: int(v) for k, v in (json.loads(text) if isinstance(text, str) else text).items()}
    except (ValueError, TypeError, AttributeError):
        return None


def checksum_total(comm, shares):
    """{name: checksum} summed over the ranks' shares ({name: share}), mod 2^64 (collective)."""
    names = sorted(shares)
    local = [int(shares[k]) for k in names]
    totals = local if comm.size == 1 else [sum(v) for v in zip(*comm.mpi.allgather(local))]
    return {k: t & _MASK64 for k, t in zip(names, totals)}


def space_problem(comm, path, need_bytes):
    """A one-line message on every rank when the file system of ``path`` has less room than a
    write of ``need_bytes`` needs (with a tenth and 1 MiB to spare), else None. Rank 0 looks and
    decides before any collective HDF5 call: a rank that ran out of room inside one (ENOSPC in
    H5Dwrite) would leave the others waiting in it forever."""
    msg = None
    if comm.rank == 0:
        folder = os.path.dirname(os.path.abspath(path))
        try:
            st = os.statvfs(folder)
            free = st.f_bavail * st.f_frsize
        except OSError as e:
            msg = f"{folder}: {e.strerror or e}"
        else:
            want = int(1.1 * need_bytes) + 2 ** 20
            if free < want:
                msg = (f"no room on the file system of {folder}: about {want / 2**20:.1f} MiB "
                       f"needed, {free / 2**20:.1f} MiB free")
    return bcast(comm, msg)


def bcast(comm, obj):
    return obj if comm.size == 1 else comm.mpi.bcast(obj, root=0)


# ---- blocks ----------------------------------------------------------------------------------

def gid_block(n_global, size, rank):
    """(lo, hi) of rank's block of global ids: [N r/P, N (r+1)/P)."""
    return (n_global * rank) // size, (n_global * (rank + 1)) // size


def block_starts(n_global, size):
    """(P+1,) int64: block r is [starts[r], starts[r+1])."""
    return np.array([(n_global * r) // size for r in range(size + 1)], dtype=np.int64)


def exscan(comm, value):
    """Exclusive prefix sum of an integer over ranks (0 on rank 0) and the total."""
    if comm.size == 1:
        return 0, int(value)
    vals = comm.mpi.allgather(int(value))
    return int(sum(vals[:comm.rank])), int(sum(vals))


# ---- attributes ------------------------------------------------------------------------------

def _json_default(o):
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON-able: {type(o).__name__}")


def to_json(obj):
    """JSON text of obj. Python floats go through repr, which round-trips float64 exactly;
    NaN and infinities become NaN / Infinity (read back by json.loads)."""
    return json.dumps(obj, default=_json_default, sort_keys=True)


def attr_value(v):
    """A value h5py can store as an attribute: str, int, float, bool and numeric arrays as
    they are; dicts, lists, tuples and None as JSON text."""
    if isinstance(v, (str, bool, int, float, np.integer, np.floating, np.bool_)):
        return v
    if isinstance(v, np.ndarray) and v.dtype.kind in "biuf":
        return v
    return to_json(v)


def set_attrs(obj, attrs):
    """Write attrs in sorted key order (the same order on every rank and in every mode, so
    parallel and serial files match)."""
    for k in sorted(attrs):
        obj.attrs[k] = attr_value(attrs[k])


def read_attrs(obj):
    """Attributes as Python values: bytes -> str, numpy scalars -> Python scalars."""
    out = {}
    for k in obj.attrs:
        v = obj.attrs[k]
        if isinstance(v, bytes):
            v = v.decode()
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


# ---- files, datasets and collective transfers --------------------------------------------------

def open_file(comm, path, mode, parallel, locking=True):
    """h5py.File on every rank of comm through the mpio driver (parallel=True), else the
    default driver on the calling rank only. locking=False skips HDF5's file lock (the mpio
    driver takes none anyway), where the HDF5 library allows it."""
    h = h5py()
    if parallel:
        return h.File(path, mode, driver="mpio", comm=comm.mpi)
    if not locking:
        try:
            return h.File(path, mode, locking=False)
        except (TypeError, ValueError):  # h5py or HDF5 too old for the option
            pass
    return h.File(path, mode)


def create_group(parent, name):
    """A group without modification times, so that two writes of the same data give the same
    bytes."""
    h = h5py()
    gcpl = h.h5p.create(h.h5p.GROUP_CREATE)
    gcpl.set_obj_track_times(False)
    gid = h.h5g.create(parent.id, name.encode(), gcpl=gcpl)
    return h.Group(gid)


def create_dataset(parent, name, shape, dtype):
    """A contiguous dataset: allocated at creation (parallel HDF5 forces this; the serial path
    asks for the same so both produce the same file), never filled (every element is written,
    a fill pass would double the I/O), no timestamps."""
    h = h5py()
    dcpl = h.h5p.create(h.h5p.DATASET_CREATE)
    dcpl.set_layout(h.h5d.CONTIGUOUS)
    dcpl.set_alloc_time(h.h5d.ALLOC_TIME_EARLY)
    dcpl.set_fill_time(h.h5d.FILL_TIME_NEVER)
    dcpl.set_obj_track_times(False)
    space = h.h5s.create_simple(tuple(int(s) for s in shape))
    tid = h.h5t.py_create(np.dtype(dtype), logical=True)
    dsid = h.h5d.create(parent.id, name.encode(), tid, space, dcpl=dcpl)
    return h.Dataset(dsid)


def dxpl(parallel):
    """Transfer property list: collective MPI-IO when parallel."""
    h = h5py()
    if not parallel:
        return None
    p = h.h5p.create(h.h5p.DATASET_XFER)
    p.set_dxpl_mpio(h.h5fd.MPIO_COLLECTIVE)
    return p


def _empty_spaces(dset):
    h = h5py()
    fspace = dset.id.get_space()
    fspace.select_none()
    mspace = h.h5s.create_simple((1,))
    mspace.select_none()
    return mspace, fspace, np.zeros(1, dtype=dset.dtype)


def _no_data(dset):
    # A dataset of zero elements (e.g. an empty pair history) has no file address: parallel
    # HDF5 fails on any transfer, even of an empty selection. Its shape is the same on every
    # rank, so every rank skips it alike.
    return dset.id.get_space().get_simple_extent_npoints() == 0


def write_rows(dset, lo, arr, xfer):
    """Write arr into rows [lo, lo + len(arr)) of dset. Every rank calls this for a collective
    transfer, a rank with nothing to write with an empty arr."""
    if _no_data(dset):
        return
    arr = np.ascontiguousarray(arr, dtype=dset.dtype)
    if arr.shape[0] == 0:
        mspace, fspace, buf = _empty_spaces(dset)
    else:
        h = h5py()
        fspace = dset.id.get_space()
        fspace.select_hyperslab((int(lo),) + (0,) * (arr.ndim - 1), arr.shape)
        mspace = h.h5s.create_simple(arr.shape)
        buf = arr
    dset.id.write(mspace, fspace, buf, dxpl=xfer)


def write_points(dset, rows, arr, xfer):
    """Write arr[i] into row rows[i] of dset (rows strictly increasing) through an HDF5 point
    selection: the index-list write, no redistribution."""
    if _no_data(dset):
        return
    arr = np.ascontiguousarray(arr, dtype=dset.dtype)
    n = arr.shape[0]
    if n == 0:
        mspace, fspace, buf = _empty_spaces(dset)
    else:
        h = h5py()
        fspace = dset.id.get_space()
        if arr.ndim == 1:
            coords = rows.astype(np.uint64).reshape(-1, 1)
        else:
            # one point per element, in the memory order of arr's rows
            trail = arr.shape[1:]
            k = int(np.prod(trail))
            coords = np.empty((n * k, arr.ndim), dtype=np.uint64)
            coords[:, 0] = np.repeat(rows.astype(np.uint64), k)
            inner = np.indices(trail).reshape(len(trail), -1).T.astype(np.uint64)
            coords[:, 1:] = np.tile(inner, (n, 1))
        fspace.select_elements(coords)
        mspace = h.h5s.create_simple((arr.size,))
        buf = arr
    dset.id.write(mspace, fspace, buf, dxpl=xfer)


def read_rows(dset, lo, hi, xfer):
    """Rows [lo, hi) of dset as a new array (collective when xfer is; hi == lo reads nothing
    but still takes part)."""
    shape = (hi - lo,) + dset.shape[1:]
    out = np.empty(shape, dtype=dset.dtype)
    if _no_data(dset):
        return out
    if hi <= lo:
        mspace, fspace, buf = _empty_spaces(dset)
        dset.id.read(mspace, fspace, buf, dxpl=xfer)
        return out
    h = h5py()
    fspace = dset.id.get_space()
    fspace.select_hyperslab((int(lo),) + (0,) * (len(shape) - 1), shape)
    mspace = h.h5s.create_simple(shape)
    dset.id.read(mspace, fspace, out, dxpl=xfer)
    return out


# ---- redistribution by gid block -----------------------------------------------------------

def _row_type(arr):
    """An MPI datatype of one row of arr (counts in rows stay far below 2^31)."""
    MPI = mpi()
    row = arr.dtype.itemsize * int(np.prod(arr.shape[1:], dtype=np.int64))
    return MPI.BYTE.Create_contiguous(row).Commit()


def _rows_1d(arr):
    """arr (n, ...) C-contiguous as a 1-D array of n opaque rows: numpy's fancy indexing of
    2-D arrays by rows is an order of magnitude slower than of 1-D ones."""
    arr = np.ascontiguousarray(arr)
    if arr.ndim == 1:
        return arr
    k = int(np.prod(arr.shape[1:], dtype=np.int64))
    return arr.reshape(arr.shape[0], k).view(np.dtype((np.void, arr.dtype.itemsize * k))).ravel()


def take_rows(arr, idx):
    """arr[idx] for whole rows, fast."""
    out = np.empty((len(idx),) + arr.shape[1:], dtype=arr.dtype)
    np.take(_rows_1d(arr), idx, out=_rows_1d(out))
    return out


def put_rows(out, idx, rows):
    """out[idx] = rows for whole rows, fast (out C-contiguous)."""
    _rows_1d(out)[idx] = _rows_1d(rows)


def _displs(counts):
    d = np.zeros(len(counts), dtype=np.int64)
    np.cumsum(counts[:-1], out=d[1:])
    return d


def _alltoallv_rows(comm, send, send_counts, recv_counts):
    """Alltoallv of whole rows of send (rows grouped by destination rank)."""
    recv = np.empty((int(recv_counts.sum()),) + send.shape[1:], dtype=send.dtype)
    rtype = _row_type(send)
    try:
        comm.mpi.Alltoallv([send, (send_counts, _displs(send_counts)), rtype],
                           [recv, (recv_counts, _displs(recv_counts)), rtype])
    finally:
        rtype.Free()
    return recv


def _check_permutation(comm, n_global, idx, n_rows, what):
    """idx (local row indices into a block of n_rows) must cover the block exactly once."""
    err = None
    if len(idx) != n_rows:
        err = f"rank {comm.rank} received {len(idx)} rows for a block of {n_rows} ({what})"
    else:
        seen = np.zeros(n_rows, dtype=bool)
        seen[idx] = True
        if not seen.all():
            err = f"duplicate gids ({what})"
    err = first_error(comm, err)
    if err is not None:
        raise ValueError(f"snapshot rows are not a permutation of gids 0..{n_global - 1}: {err}")


def _check_range(comm, n_global, gid):
    bad = len(gid) > 0 and (int(gid.min()) < 0 or int(gid.max()) >= n_global)
    err = first_error(comm, f"rank {comm.rank} holds gids outside [0, {n_global})" if bad else None)
    if err is not None:
        raise ValueError(f"snapshot rows are not a permutation of gids 0..{n_global - 1}: {err}")


def to_gid_blocks(comm, n_global, gid, fields):
    """Send every row to the rank owning its gid block [N r/P, N(r+1)/P): one alltoallv for
    the gids and one per field (contiguous arrays: packing rows of all fields into records
    costs more in strided copies than the extra calls). Returns (lo, {name: block array in gid
    order}) on every rank.

    Raises ValueError on every rank when the gids are not a permutation of 0..N-1.
    """
    P = comm.size
    lo, hi = gid_block(n_global, P, comm.rank)
    _check_range(comm, n_global, gid)
    if P == 1:
        idx, order = gid, None
    else:
        # the r with floor(N r/P) <= g < floor(N (r+1)/P), in integers
        dest = ((gid + 1) * P - 1) // n_global
        # numpy's stable sort of 16-bit keys is a radix sort: linear in the rows
        order = np.argsort(dest.astype(np.int16 if P < 2 ** 15 else np.int64), kind="stable")
        send_counts = np.bincount(dest, minlength=P).astype(np.int64)
        recv_counts = np.empty(P, dtype=np.int64)
        comm.mpi.Alltoall(send_counts, recv_counts)
        idx = _alltoallv_rows(comm, gid[order], send_counts, recv_counts) - lo
    _check_permutation(comm, n_global, idx, hi - lo, f"gid block [{lo}, {hi})")
    out = {}
    for name, arr in fields.items():
        rows = arr if P == 1 else _alltoallv_rows(comm, take_rows(arr, order),
                                                  send_counts, recv_counts)
        o = np.empty((hi - lo,) + arr.shape[1:], dtype=arr.dtype)
        put_rows(o, idx, rows)
        out[name] = o
    return lo, out


def gather_to_root(comm, n_global, gid, fields):
    """Rank 0 gets every row in gid order (the fallback when h5py has no MPI): dict of
    (N, ...) arrays on rank 0, None elsewhere."""
    _check_range(comm, n_global, gid)
    if comm.size == 1:
        _, out = to_gid_blocks(comm, n_global, gid, fields)
        return out
    counts = np.array(comm.mpi.allgather(len(gid)), dtype=np.int64)
    root = comm.rank == 0

    def gather(arr):
        rtype = _row_type(arr)
        try:
            if root:
                recv = np.empty((int(counts.sum()),) + arr.shape[1:], dtype=arr.dtype)
                comm.mpi.Gatherv([arr, len(arr), rtype], [recv, (counts, _displs(counts)), rtype], root=0)
                return recv
            comm.mpi.Gatherv([arr, len(arr), rtype], None, root=0)
            return None
        finally:
            rtype.Free()

    g = gather(np.ascontiguousarray(gid))
    err = None
    if root:
        if len(g) != n_global:
            err = f"{len(g)} rows for N = {n_global}"
        else:
            seen = np.zeros(n_global, dtype=bool)
            seen[g] = True
            if not seen.all():
                err = "duplicate gids"
    err = bcast(comm, err)
    if err is not None:
        raise ValueError(f"snapshot rows are not a permutation of gids 0..{n_global - 1}: {err}")
    out = {}
    for name, arr in fields.items():
        rows = gather(np.ascontiguousarray(arr))
        if root:
            o = np.empty((n_global,) + arr.shape[1:], dtype=arr.dtype)
            put_rows(o, g, rows)
            out[name] = o
    return out if root else None


# ---- durable files -----------------------------------------------------------------------------

def fsync_path(path, directory=False):
    """fsync a file (or a folder, so that a rename in it is durable)."""
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_text_atomic(path, text):
    """Write text through a temporary file and a rename: a reader sees the old file or the new
    one, never half of one."""
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        f.write(text)
    os.replace(tmp, path)
