"""Checkpoints: the whole state by global id, readable on any number of ranks.

File layout (``format = "mpipack-checkpoint"``, ``format_version = 1``)::

    /                      attributes: format, format_version, n (N), dim (b), ranks (of the
                           writer), version (mpipack), scalars (JSON text of the scalars dict),
                           and the caller's attrs (scene as JSON text, ...; dict and list values
                           as JSON text)
    /particles/<name>      (N, ...) one dataset per per-particle array, row = gid:
        x                  (N, b)   float64   X^n
        x_prev             (N, b)   float64   X^{n-1}
        x_lin              (N, b)   float64   NAP/NAV's linearisation point (only if given)
        diam               (N,)     float64
        <any other>        (N, ...)           any further per-particle array of the block
    /history/offset        (N+1,)   int64     the partners of gid g are entries
                                              offset[g] .. offset[g+1] (offset[0] = 0, offset[N] = K)
    /history/gid           (K,)     int64     partner gids (lambda > 0), each pair under both
    /history/lambda        (K,)     float64   its particles
    /history/<name>        (K, ...)           any further ``hist_<name>`` array of the block

A rank's ``block`` (what write_checkpoint takes and read_checkpoint returns) is its run of
consecutive gids in rank order, rank r's starting at ``gid_lo``, rows in gid order::

    gid_lo        int
    x, x_prev     (m, b) float64; x_lin (m, b) optional; diam (m,); any other (m, ...) array
    hist_count    (m,) int64    partners of particle gid_lo + i
    hist_gid      (k,) int64    k = sum(hist_count); entries sum(hist_count[:i]) .. + hist_count[i]
    hist_lambda   (k,) float64  belong to particle gid_lo + i
    hist_<name>   (k, ...)      any other per-entry array

The writer accepts blocks of any sizes (offsets by an exclusive scan); the reader on P ranks
returns rank r the block [N r/P, N (r+1)/P), whatever P the writer had.

``scalars`` (iteration, flags, counters, controller state) is one JSON attribute: json writes
Python floats with repr, which reads back to the same float64 bit for bit (NaN and infinities
included); numpy scalars and arrays are converted to Python numbers and lists first. As with
any JSON, dict keys come back as str (in sorted order) and tuples as lists.

Atomic: the ranks write ``.<name>.tmp`` in the same folder collectively, flush (MPI_File_sync)
and close; rank 0 fsyncs it, renames it over ``path`` (os.replace) and fsyncs the folder. Until
that rename the previous checkpoint is untouched, so a rank killed at any point of a write
leaves the previous one readable.

Validation: a missing, empty, non-HDF5, truncated or damaged file, an HDF5 file of another
kind, a wrong format version or inconsistent shapes raise ``CheckpointError`` with a one-line
message naming the file, on every rank (rank 0 checks the header and broadcasts its verdict;
errors while reading the blocks are agreed on collectively).
"""

import json
import os
import time

import numpy as np

from . import _h5

FORMAT = "mpipack-checkpoint"
FORMAT_VERSION = 1
REQUIRED = ("x", "x_prev", "diam", "hist_count", "hist_gid", "hist_lambda")

# Test-only: called as _test_hook(stage, comm) at "temp_open", "data_written" (before the
# temporary file is closed) and "temp_closed" (before the rename), so a test can kill a rank
# mid-write. None in normal runs.
_test_hook = None


class CheckpointError(Exception):
    """An unusable checkpoint, or a checkpoint that could not be written. One-line message
    that names the file."""


def _hook(stage, comm):
    if _test_hook is not None:
        _test_hook(stage, comm)


def _split(block):
    """(per-particle arrays, per-entry arrays) of a block, keyed by their dataset names."""
    parts, hist = {}, {}
    for k, v in block.items():
        if k in ("gid_lo", "hist_count") or v is None:
            continue
        if k.startswith("hist_"):
            hist[k[len("hist_"):]] = np.asarray(v)
        else:
            parts[k] = np.asarray(v)
    return parts, hist


def _temp_path(path):
    d, name = os.path.split(os.path.abspath(path))
    return os.path.join(d, f".{name}.tmp")


def write_checkpoint(comm, path, n_global, dim, block, scalars, attrs, *, parallel=None):
    """Write a checkpoint atomically and collectively (every rank calls it).

    Parameters
    ----------
    comm : mpipack.parallel.comm.Comm (``mpi``, ``rank``, ``size``)
    path : the checkpoint file (replaced atomically)
    n_global, dim : N and b
    block : this rank's gid block (see the module docstring); blocks consecutive in rank order
    scalars : JSON-able dict (rank 0's is written)
    attrs : file attributes (rank 0's are written)
    parallel : None = MPI-IO when h5py has MPI and there are several ranks; False = ranks write
        their rows in turn with serial h5py (no MPI-IO); True = MPI-IO even on one rank

    Returns the wall time of the write in seconds, the same value on every rank (rank 0's,
    from entry to the durable rename).
    """
    t0 = time.perf_counter()
    path = os.fspath(path)
    n_global, dim = int(n_global), int(dim)
    has_mpi = _h5.h5py_has_mpi()
    if parallel is None:
        parallel = has_mpi and comm.size > 1
    parallel = bool(parallel and has_mpi)

    # ---- check the blocks (collectively: a bad block on one rank stops every rank) ----------
    err = None
    missing = [k for k in REQUIRED if block.get(k) is None]
    gid_lo = int(block.get("gid_lo", -1))
    if missing:
        err = f"block on rank {comm.rank} lacks {missing}"
        parts, hist, m, count = {}, {}, 0, np.zeros(0, np.int64)
    elif "hist_offset" in block:
        err = "hist_offset is reserved (the file's history/offset is derived from hist_count)"
        parts, hist, m, count = {}, {}, 0, np.zeros(0, np.int64)
    else:
        parts, hist = _split(block)
        count = np.ascontiguousarray(block["hist_count"], dtype=np.int64).ravel()
        m = len(count)
        for k, v in parts.items():
            if v.ndim == 0 or v.shape[0] != m:
                err = err or f"{k} has shape {v.shape}, hist_count has {m} rows (rank {comm.rank})"
        k_local = int(count.sum())
        for k, v in hist.items():
            if v.ndim == 0 or v.shape[0] != k_local:
                err = err or f"hist_{k} has {v.shape[0] if v.ndim else 0} entries, sum(hist_count) = {k_local} (rank {comm.rank})"
        for k in ("x", "x_prev", "x_lin"):
            if k in parts and (parts[k].ndim != 2 or parts[k].shape[1] != dim):
                err = err or f"{k} has shape {parts[k].shape}, expected (m, {dim})"
        if np.any(count < 0):
            err = err or f"negative hist_count on rank {comm.rank}"
    k_local = int(count.sum())
    m_off, m_total = _h5.exscan(comm, m)
    k_off, k_total = _h5.exscan(comm, k_local)
    if err is None and m_off != gid_lo:
        err = f"rank {comm.rank} block starts at gid {gid_lo}, ranks before it hold {m_off} rows"
    sig = (sorted((k, v.dtype.str, v.shape[1:]) for k, v in parts.items()),
           sorted((k, v.dtype.str, v.shape[1:]) for k, v in hist.items()))
    sigs = comm.mpi.allgather((m, sig)) if comm.size > 1 else [(m, sig)]
    ref = next((s for mm, s in sigs if mm > 0), sigs[0][1])
    if err is None and m_total != n_global:
        err = f"blocks hold {m_total} particles, N = {n_global}"
    if err is None and ([a[0] for a in sig[0]], [a[0] for a in sig[1]]) != \
            ([a[0] for a in ref[0]], [a[0] for a in ref[1]]):
        err = f"block arrays differ between ranks: {sig} vs {ref}"
    if err is None and m > 0 and sig != ref:
        err = f"block dtypes or shapes differ between ranks: {sig} vs {ref}"
    err = _h5.first_error(comm, err)
    if err is not None:
        raise ValueError(f"{path}: checkpoint not written: {err}")
    # empty ranks take the dtype and trailing shape of the first non-empty one
    parts = {k: np.ascontiguousarray(parts[k], dtype=dt).reshape((-1,) + tuple(tr))
             for k, dt, tr in ref[0]}
    hist = {k: np.ascontiguousarray(hist[k], dtype=dt).reshape((-1,) + tuple(tr))
            for k, dt, tr in ref[1]}
    offsets = np.empty(m + (1 if comm.rank == comm.size - 1 else 0), dtype=np.int64)
    offsets[0:m] = k_off + np.cumsum(count) - count
    if comm.rank == comm.size - 1:
        offsets[m] = k_total

    file_attrs = dict(_h5.bcast(comm, dict(attrs)) or {})
    scalars_json = _h5.bcast(comm, _h5.to_json(scalars) if comm.rank == 0 else None)
    file_attrs.setdefault("ranks", comm.size)
    file_attrs.setdefault("version", _package_version())
    # checksums of every dataset, whatever the partition (``_h5.checksum_rows``), checked on read
    shares = {f"particles/{k}": _h5.checksum_rows(v, gid_lo) for k, v in parts.items()}
    shares.update({f"history/{k}": _h5.checksum_rows(v, k_off) for k, v in hist.items()})
    shares["history/offset"] = _h5.checksum_rows(offsets, gid_lo)
    checksums = _h5.checksum_total(comm, shares)
    file_attrs.update(format=FORMAT, format_version=FORMAT_VERSION, n=n_global, dim=dim,
                      scalars=scalars_json, checksums=json.dumps({k: str(v) for k, v in checksums.items()}))
    layout = {"particles": {k: ((n_global,) + v.shape[1:], v.dtype) for k, v in parts.items()},
              "history": {k: ((k_total,) + v.shape[1:], v.dtype) for k, v in hist.items()}}
    layout["history"]["offset"] = ((n_global + 1,), np.dtype(np.int64))
    rows = {("particles", k): (gid_lo, v) for k, v in parts.items()}
    rows.update({("history", k): (k_off, v) for k, v in hist.items()})
    rows[("history", "offset")] = (gid_lo, offsets)

    tmp = _temp_path(path)
    need = sum(int(np.prod(shape, dtype=np.int64)) * np.dtype(dt).itemsize
               for group in layout.values() for shape, dt in group.values())
    err = _h5.space_problem(comm, path, need)  # the previous checkpoint stays until the rename
    if err is not None:
        raise CheckpointError(f"{path}: checkpoint not written: {err}")
    err = None
    try:
        if parallel:
            _write_parallel(comm, tmp, layout, rows, file_attrs)
        else:
            _write_in_turn(comm, tmp, layout, rows, file_attrs)
    except Exception as e:
        err = f"{path}: checkpoint not written: {_h5.one_line(e)}"
    err = _h5.first_error(comm, err)
    if err is None:
        _hook("temp_closed", comm)
        if comm.rank == 0:
            try:
                # MPI_File_sync (the flush) makes the data durable on parallel file systems; on
                # a local one, fsync by path makes sure of it whatever the MPI-IO layer did
                _h5.fsync_path(tmp)
                os.replace(tmp, path)
                _h5.fsync_path(os.path.dirname(os.path.abspath(path)), directory=True)
            except OSError as e:
                err = f"{path}: checkpoint not written: {_h5.one_line(e)}"
        err = _h5.bcast(comm, err)
    if err is not None:
        if comm.rank == 0:
            try:
                os.unlink(tmp)
            except OSError:
                pass
        raise CheckpointError(err)
    return float(_h5.bcast(comm, time.perf_counter() - t0))


def _create_all(f, layout, file_attrs):
    ds = {}
    for gname in ("particles", "history"):
        g = _h5.create_group(f, gname)
        for k in sorted(layout[gname]):
            shape, dt = layout[gname][k]
            ds[(gname, k)] = _h5.create_dataset(g, k, shape, dt)
    _h5.set_attrs(f, file_attrs)
    return ds


def _write_parallel(comm, tmp, layout, rows, file_attrs):
    xfer = _h5.dxpl(True)
    with _h5.open_file(comm, tmp, "w", True) as f:
        _hook("temp_open", comm)
        ds = _create_all(f, layout, file_attrs)
        for key in sorted(rows):
            lo, v = rows[key]
            _h5.write_rows(ds[key], lo, v, xfer)
        _hook("data_written", comm)
        f.flush()


def _write_in_turn(comm, tmp, layout, rows, file_attrs):
    """Without MPI-IO: rank 0 creates the file, then each rank in turn opens it and writes its
    own rows (no rank holds more than its block)."""
    err = None
    if comm.rank > 0:
        err = comm.mpi.recv(source=comm.rank - 1, tag=77)
    if err is None:
        try:
            with _h5.open_file(comm, tmp, "w" if comm.rank == 0 else "r+", False) as f:
                if comm.rank == 0:
                    _hook("temp_open", comm)
                    ds = _create_all(f, layout, file_attrs)
                else:
                    ds = {(g, k): f[g][k] for g in ("particles", "history") for k in f[g]}
                for key in sorted(rows):
                    lo, v = rows[key]
                    _h5.write_rows(ds[key], lo, v, None)
                _hook("data_written", comm)
        except Exception as e:
            err = _h5.one_line(e)
    if comm.rank < comm.size - 1:
        comm.mpi.send(err, dest=comm.rank + 1, tag=77)
    err = _h5.bcast(comm, err) if comm.size == 1 else comm.mpi.bcast(err, root=comm.size - 1)
    if err is not None:
        raise OSError(err)


def _package_version():
    try:
        from mpipack import __version__
        return __version__
    except ImportError:  # pragma: no cover
        return "unknown"


# ---- reading -----------------------------------------------------------------------------------

def _header(path):
    """Rank 0: check the file and return its header dict, or raise CheckpointError."""
    def bad(problem):
        return CheckpointError(f"{path}: {problem}")

    if not os.path.exists(path):
        raise bad("no such file")
    if os.path.isdir(path):
        raise bad("is a folder, not a checkpoint file")
    size = os.path.getsize(path)
    if size == 0:
        raise bad("empty file, not a checkpoint")
    h5py = _h5.h5py()
    try:
        is_h5 = h5py.is_hdf5(path)
    except Exception as e:
        raise bad(f"cannot be read: {_h5.one_line(e)}")
    if not is_h5:
        raise bad("not an HDF5 file, not an mpipack checkpoint")
    try:
        f = h5py.File(path, "r")
    except Exception as e:
        raise bad(f"truncated or damaged HDF5 file ({_h5.one_line(e)})")
    with f:
        try:
            attrs = _h5.read_attrs(f)
        except Exception as e:
            raise bad(f"damaged HDF5 file, attributes unreadable ({_h5.one_line(e)})")
        fmt = attrs.get("format")
        if fmt != FORMAT:
            what = f"format attribute {fmt!r}" if fmt is not None else "no format attribute"
            raise bad(f"not an mpipack checkpoint ({what})")
        ver = attrs.get("format_version")
        if ver != FORMAT_VERSION:
            raise bad(f"checkpoint format version {ver}, this mpipack reads version {FORMAT_VERSION}")
        try:
            n, dim = int(attrs["n"]), int(attrs["dim"])
            scalars = json.loads(attrs["scalars"])
            parts = {k: (f["particles"][k].dtype, f["particles"][k].shape) for k in f["particles"]}
            hist = {k: (f["history"][k].dtype, f["history"][k].shape) for k in f["history"]}
        except Exception as e:
            raise bad(f"damaged checkpoint ({_h5.one_line(e)})")
        for k in ("x", "x_prev", "diam"):
            if k not in parts:
                raise bad(f"damaged checkpoint: no particles/{k}")
        for k in ("offset", "gid", "lambda"):
            if k not in hist:
                raise bad(f"damaged checkpoint: no history/{k}")
        for k, (dt, shape) in parts.items():
            if len(shape) == 0 or shape[0] != n:
                raise bad(f"damaged checkpoint: particles/{k} has shape {shape}, N = {n}")
        if parts["x"][1] != (n, dim) or parts["x_prev"][1] != (n, dim):
            raise bad(f"damaged checkpoint: x has shape {parts['x'][1]}, expected ({n}, {dim})")
        if hist["offset"][1] != (n + 1,):
            raise bad(f"damaged checkpoint: history/offset has shape {hist['offset'][1]}, expected ({n + 1},)")
        k_total = hist["gid"][1][0] if hist["gid"][1] else -1
        for k, (dt, shape) in hist.items():
            if k != "offset" and (len(shape) == 0 or shape[0] != k_total):
                raise bad(f"damaged checkpoint: history/{k} has shape {shape}, history/gid {hist['gid'][1]}")
        try:
            ends = f["history"]["offset"][[0, n]] if n > 0 else f["history"]["offset"][:1]
        except Exception as e:
            raise bad(f"damaged checkpoint, unreadable data ({_h5.one_line(e)})")
        if int(ends[0]) != 0 or int(ends[-1]) != k_total:
            raise bad(f"damaged checkpoint: history offsets run {int(ends[0])}..{int(ends[-1])}, "
                      f"{k_total} entries stored")
    del attrs["scalars"]
    return {"n": n, "dim": dim, "scalars": scalars, "attrs": attrs,
            "parts": sorted(parts), "hist": sorted(k for k in hist if k != "offset")}


def read_checkpoint(comm, path, *, parallel=None):
    """Read a checkpoint onto comm's ranks, collectively.

    Returns (block, scalars, attrs): rank r's block of gids [N r/P, N (r+1)/P) as described
    in the module docstring (``gid_lo``, every per-particle array, ``hist_count``, ``hist_gid``,
    ``hist_lambda`` and any other ``hist_<name>``), the scalars dict, and the file attributes
    (without ``scalars``; including format, format_version, n, dim, ranks, version). Raises
    CheckpointError (one line, naming the file) on every rank if the file is unusable.
    """
    path = os.fspath(path)
    has_mpi = _h5.h5py_has_mpi()
    if parallel is None:
        parallel = has_mpi and comm.size > 1
    parallel = bool(parallel and has_mpi)
    head, err = None, None
    if comm.rank == 0:
        try:
            head = _header(path)
        except CheckpointError as e:
            err = str(e)
    head, err = _h5.bcast(comm, (head, err))
    if err is not None:
        raise CheckpointError(err)
    n = head["n"]
    lo, hi = _h5.gid_block(n, comm.size, comm.rank)
    block = {"gid_lo": lo}
    err = None
    try:
        xfer = _h5.dxpl(parallel)
        with _h5.open_file(comm, path, "r", parallel) as f:
            for k in head["parts"]:
                block[k] = _h5.read_rows(f["particles"][k], lo, hi, xfer)
            off = _h5.read_rows(f["history"]["offset"], lo, hi + 1, xfer)
            k_lo, k_hi = (int(off[0]), int(off[-1]))
            if np.any(np.diff(off) < 0) or k_lo > k_hi:
                # still take part in the collective reads below, with nothing to read
                err = f"{path}: damaged checkpoint: history offsets decrease in gids [{lo}, {hi})"
                k_lo = k_hi = 0
            for k in head["hist"]:
                block["hist_" + k] = _h5.read_rows(f["history"][k], k_lo, k_hi, xfer)
            block["hist_count"] = np.diff(off).astype(np.int64)
    except Exception as e:
        err = err or f"{path}: unreadable checkpoint ({_h5.one_line(e)})"
    err = _h5.first_error(comm, err)
    if err is not None:
        raise CheckpointError(err)
    stored = head["attrs"].get("checksums")
    if stored is not None:  # files of before the checksums have none
        shares = {f"particles/{k}": _h5.checksum_rows(block[k], lo) for k in head["parts"]}
        shares.update({f"history/{k}": _h5.checksum_rows(block["hist_" + k], k_lo) for k in head["hist"]})
        last = comm.rank == comm.size - 1  # the offsets' final row is the last rank's
        shares["history/offset"] = _h5.checksum_rows(off if last else off[:-1], lo)
        got = _h5.checksum_total(comm, shares)
        try:
            want = {k: int(v) for k, v in (json.loads(stored) if isinstance(stored, str) else stored).items()}
        except (ValueError, TypeError, AttributeError):
            want = None
        bad = sorted(k for k in got if want is None or want.get(k) != got[k])
        if bad:
            raise CheckpointError(f"{path}: damaged checkpoint: {', '.join(bad[:3])} do not match their checksum")
    return block, head["scalars"], head["attrs"]
