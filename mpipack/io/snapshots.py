"""Snapshots: one HDF5 file per run, datasets in global-id order, written collectively.

File layout (``format = "mpipack-snapshots"``, ``format_version = 1``), row i of every
per-particle dataset is global id i::

    /                          attributes: format, format_version, n (N), dim (b), ranks (of the
                               run that last wrote the file), version (mpipack), and the run's
                               file_attrs: scene (JSON text), parameters, ...; dict and list
                               values are stored as JSON text
    /topology/vertex   (N,)    int32 (int64 when N >= 2^31): 0..N-1, the polyvertex connectivity
                               the XDMF file refers to (written once per file)
    /snapshots/<iteration>/    one group per snapshot, named by the iteration zero-padded to 10
                               digits (so names sort in time order); attributes: iteration,
                               wall_seconds, relative_change, max_overlap, W (what the caller
                               passes)
        position      (N, b)   float64   X_i
        diameter      (N,)     float64   d_i
        pressure      (N,)     float64   mu_i = sum_j lambda_ij
        contacts      (N,)     int32     partners (and container walls) with lambda > 0
        wall_force    (N,)     float64   sum_w lambda_iw |grad phi_iw|: the container's push on
                                         the sphere (runs in a container only)
        net_force     (N,)     float64   |g_i|, g_i = (X_i - Xbar) + sum_j lambda_ij grad_i phi_ij:
                                         the sphere's row of the KKT residual (run snapshots)
        (attribute checksums: JSON {dataset: checksum of its 64-bit words, weighted by
         position (io/_h5.checksum_rows)}, "pairs/gid" and "pairs/lambda" included; readers
         refuse a snapshot whose data do not match: read_snapshot, read_pairs, mpipack post)
        radius        (N,)     float64   d_i / 2, added by the writer (ParaView scales sphere
                                         glyphs by it; the Xdmf3 readers skip XDMF Function
                                         items, so it is stored, not computed in the XDMF)
        position_xy   (N, 2)   float64   1D runs only: (x, 0), for ParaView (see xdmf.py)
        <any other>   (N, ...)           any further field the caller passes, its dtype kept
        pairs/                           the contact network, when the caller gives it (every
                                         run snapshot; absent = not recorded, empty = no contact)
            gid       (M, 2)   int64     (gid_i, gid_j), gid_i < gid_j, of every pair with
                                         lambda_ij > 0, rows sorted by (gid_i, gid_j): the same
                                         file for any number of ranks; M may be 0
            lambda    (M,)     float64   lambda_ij of each row
                                         (read_pairs(path, iteration) reads them back)

Datasets are contiguous and unfiltered (what parallel HDF5 writes fastest), allocated when
created and never pre-filled. Beside the file, rewritten by rank 0 after each snapshot:
``<stem>.xmf`` (the spheres) and ``<stem>_contacts.xmf`` (the contact network, when snapshots
hold pairs) let ParaView open the series directly (xdmf.py); ``view.py`` (written when the
writer opens the file, paraview.py) shows them: ``pvbatch view.py --png view.png``.

How rows reach gid order. Particles are owned by space, so a rank holds an arbitrary set of
gids. Two ways are implemented (``method``):

    "redistribute" (default)  alltoallv (one for the gids, one per field) sends each row to
                              the rank owning its gid block [N r/P, N (r+1)/P); each rank then
                              writes one contiguous hyperslab per dataset, collectively
    "points"                  each rank sorts its rows by gid and writes them through an HDF5
                              point selection (an index-list write, no communication)

Pairs go the first way with either method: each to the owner of gid_i's block (one alltoallv
for the gids, one for lambda), sorted there, written at the offset an exclusive scan of the
counts gives.

Measured with ``tools/io_bench.py --methods`` at N = 1e6 on 2 ranks (gids scattered at random
over the ranks, as after a Gaussian start; three runs of 3-5 writes, medians, on a shared 2-core
machine): 2D redistribute 0.29-0.40 s, points 4.0-9.0 s; 3D redistribute 0.14-0.48 s, points
5.1-10.3 s per snapshot. The point selection costs HDF5 one coordinate tuple per element and
MPI-IO a scattered file view; the alltoallv moves each row once through shared memory. So
"redistribute" is the default; "points" is kept for comparison.

Appending: opening an existing file continues its series (a restarted run); the file's N and
dim must match. ``truncate_after=K`` first deletes the snapshots after iteration K (a run
restarted from the checkpoint of iteration K rewrites them); rewriting an existing iteration
replaces it. The file is opened for each snapshot and closed after it, so a run killed between
two snapshots leaves a valid file holding every complete one, and ParaView can read it while the
run goes on (a kill during a snapshot write can leave the file damaged: HDF5 1.10 does not
journal its metadata; restarts rely on the checkpoint, which is atomic). The writer takes no HDF5 file lock (the mpio driver takes none either): a viewer or a
notebook holding the file open must not make the run fail.

Without MPI in h5py (``h5py.get_config().mpi`` False), or with ``parallel=False``, rows are
gathered by gid on rank 0, which writes the same file alone (one-line warning on rank 0 when
the run has several ranks). A one-rank run takes that path too, without MPI-IO.
"""

import os
import sys
import time

import numpy as np

from . import _h5, paraview as _paraview, xdmf as _xdmf

FORMAT = "mpipack-snapshots"
FORMAT_VERSION = 1
METHODS = ("redistribute", "points")


class SnapshotError(ValueError):
    """A snapshot file that cannot be used or written; the message is one line naming it."""


def _group_name(iteration):
    return f"{int(iteration):010d}"


def _package_version():
    try:
        from mpipack import __version__
        return __version__
    except ImportError:  # pragma: no cover
        return "unknown"


class SnapshotWriter:
    """Writes snapshots of a run into one HDF5 file (layout in the module docstring).

    Parameters
    ----------
    comm : mpipack.parallel.comm.Comm (only ``mpi``, ``rank``, ``size`` are used); collective
    path : the ``.h5`` file; created, or appended to if it exists
    n_global, dim : N and b
    file_attrs : dict of file attributes (scene as JSON text, parameters, ...); rank 0's are used
    method : "redistribute" (default) or "points", see the module docstring
    parallel : None = MPI-IO when h5py has MPI and the run has several ranks; False = through
        rank 0; True = MPI-IO even on one rank
    xdmf : write ``<stem>.xmf`` beside the file after each snapshot
    truncate_after : drop snapshots with iteration > this (restart), None keeps all
    """

    def __init__(self, comm, path, n_global, dim, file_attrs, *, method="redistribute",
                 parallel=None, xdmf=True, truncate_after=None):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, not {method!r}")
        self.comm = comm
        # rank 0's path: every rank must open the same file
        self.path = _h5.bcast(comm, os.path.abspath(os.fspath(path)))
        self.n_global = int(n_global)
        self.dim = int(dim)
        self.method = method
        self.xdmf_path = os.path.splitext(self.path)[0] + ".xmf" if xdmf else None
        has_mpi = _h5.h5py_has_mpi()
        if parallel is None:
            parallel = has_mpi and comm.size > 1
        elif parallel and not has_mpi:
            parallel = False
        if not parallel and comm.size > 1 and not has_mpi and comm.rank == 0:
            print("mpipack: warning: h5py has no MPI support; snapshots are gathered and "
                  "written by rank 0", file=sys.stderr, flush=True)
        self.parallel = bool(parallel)
        self._xfer = None
        self._entries = None        # rank 0: the file's snapshots, for the XDMF file
        self._topology_dtype = np.dtype(np.int32 if self.n_global < 2 ** 31 else np.int64)
        self.closed = False
        self.last_seconds = 0.0     # wall time of the last write() on this rank

        attrs = dict(_h5.bcast(comm, dict(file_attrs)) or {})
        attrs.setdefault("ranks", comm.size)
        attrs.setdefault("version", _package_version())
        attrs.update(format=FORMAT, format_version=FORMAT_VERSION, n=self.n_global,
                     dim=self.dim)
        err = None
        if comm.rank == 0:
            try:
                self._prepare(attrs, truncate_after)
            except SnapshotError as e:
                err = str(e)
            except Exception as e:  # an HDF5 or OS error: the same one-line form
                err = self._msg(f"cannot open for writing: {_h5.one_line(e)}")
        err = _h5.bcast(comm, err)
        if err is not None:
            raise SnapshotError(err)

    # ---- set-up (rank 0, serial) ---------------------------------------------------------------
    def _msg(self, problem):
        return f"{self.path}: {problem}"

    def _prepare(self, attrs, truncate_after):
        h5py = _h5.h5py()
        if os.path.exists(self.path):
            if not h5py.is_hdf5(self.path):
                raise SnapshotError(self._msg("exists and is not an HDF5 file; not overwriting it"))
            f = _h5.open_file(self.comm, self.path, "r+", False, locking=False)
            try:
                fmt = f.attrs.get("format")
                fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
                if fmt != FORMAT:
                    raise SnapshotError(self._msg(
                        f"exists and is not an mpipack snapshot file (format {fmt!r}); not appending"))
                ver = int(f.attrs.get("format_version", -1))
                if ver != FORMAT_VERSION:
                    raise SnapshotError(self._msg(
                        f"snapshot format version {ver}, this mpipack writes version {FORMAT_VERSION}"))
                n, dim = int(f.attrs["n"]), int(f.attrs["dim"])
                if (n, dim) != (self.n_global, self.dim):
                    raise SnapshotError(self._msg(
                        f"holds N = {n}, dim = {dim}; this run has N = {self.n_global}, "
                        f"dim = {self.dim}"))
                snaps = f.require_group("snapshots")
                if truncate_after is not None:
                    for name in list(snaps):
                        if int(snaps[name].attrs["iteration"]) > int(truncate_after):
                            del snaps[name]
                _h5.set_attrs(f, attrs)
                _, _, self._entries, _ = _xdmf.scan(f)
            finally:
                f.close()
        else:
            with _h5.open_file(self.comm, self.path, "w", False, locking=False) as f:
                _h5.create_group(f, "snapshots")
                _h5.set_attrs(f, attrs)
            self._entries = []
        if self._entries:
            self._write_xdmf()
        if self.xdmf_path is not None:
            try:
                _paraview.write_view(os.path.dirname(self.path),
                                     os.path.splitext(os.path.basename(self.path))[0])
            except OSError as e:
                raise SnapshotError(f"{_paraview.view_path(os.path.dirname(self.path))}: not written: "
                                    f"{_h5.one_line(e.strerror or e)}") from None

    def _write_xdmf(self):
        if self.xdmf_path is not None and self.comm.rank == 0:
            _xdmf.write(self.xdmf_path, self.path, self.n_global, self.dim, self._entries,
                        topology_dtype=self._topology_dtype.str)

    # ---- writing -------------------------------------------------------------------------------
    def _check(self, gid, fields):
        """Same names, dtypes and trailing shapes on every rank (taken from the first rank
        holding rows; empty ranks are cast to them), lengths equal to len(gid)."""
        comm = self.comm
        err = None
        for name, a in fields.items():
            if a.ndim == 0 or a.shape[0] != len(gid):
                err = f"field {name!r} has shape {a.shape} for {len(gid)} gids on rank {comm.rank}"
        if len(gid) and "position" in fields and fields["position"].shape[1:] != (self.dim,):
            err = err or f"position has shape {fields['position'].shape}, expected (n, {self.dim})"
        sig = sorted((name, a.dtype.str, a.shape[1:]) for name, a in fields.items())
        sigs = comm.mpi.allgather((len(gid), sig)) if comm.size > 1 else [(len(gid), sig)]
        ref = next((s for m, s in sigs if m > 0), sigs[0][1])
        if [n for n, _, _ in sig] != [n for n, _, _ in ref]:
            err = err or f"fields differ between ranks: {[n for n, _, _ in sig]} vs {[n for n, _, _ in ref]}"
        elif len(gid) > 0 and sig != ref:
            err = err or f"field dtypes or shapes differ between ranks: {sig} vs {ref}"
        err = _h5.first_error(comm, err)
        if err is not None:
            raise ValueError(f"{self.path}: snapshot not written: {err}")
        return {name: np.ascontiguousarray(fields[name], dtype=dt).reshape((-1,) + tuple(tr))
                for name, dt, tr in ref}

    def _check_pairs(self, pairs):
        """(gid (m, 2) int64, lambda (m,) float64) of this rank's pairs, or None when no rank
        gives pairs (a rank giving None while others give pairs gives none). Collective."""
        comm = self.comm
        err, pg, pl = None, np.empty((0, 2), np.int64), np.empty(0, np.float64)
        if pairs is not None:
            try:
                gi, gj, lam = pairs
                gi = np.asarray(gi, dtype=np.int64).ravel()
                gj = np.asarray(gj, dtype=np.int64).ravel()
                pl = np.ascontiguousarray(lam, dtype=np.float64).ravel()
            except (TypeError, ValueError) as e:
                err = f"pairs must be (gid_i, gid_j, lambda) arrays: {_h5.one_line(e)}"
            else:
                if not (len(gi) == len(gj) == len(pl)):
                    err = f"pairs have {len(gi)}, {len(gj)}, {len(pl)} rows on rank {comm.rank}"
                elif len(gi) and (gi.min() < 0 or gj.max() >= self.n_global or np.any(gi >= gj)):
                    err = f"pairs on rank {comm.rank} are not 0 <= gid_i < gid_j < {self.n_global}"
                else:
                    pg = np.column_stack([gi, gj]) if len(gi) else pg
        given = comm.mpi.allreduce(int(pairs is not None)) if comm.size > 1 else int(pairs is not None)
        err = _h5.first_error(comm, err)
        if err is not None:
            raise ValueError(f"{self.path}: snapshot not written: {err}")
        return (np.ascontiguousarray(pg), pl) if given else None

    def _sorted_pairs(self, pg, pl):
        """(first row, total M, rows, lambdas): the pairs sorted by (gid_i, gid_j), this rank's
        contiguous share of them (parallel: the pairs of its gid block; serial: all on rank 0,
        none elsewhere). Collective; duplicate pairs raise ValueError on every rank."""
        comm, P = self.comm, self.comm.size
        if P > 1 and self.parallel:
            dest = ((pg[:, 0] + 1) * P - 1) // self.n_global
            order = np.argsort(dest, kind="stable")
            send = np.bincount(dest, minlength=P).astype(np.int64)
            recv = np.empty(P, dtype=np.int64)
            comm.mpi.Alltoall(send, recv)
            pg = _h5._alltoallv_rows(comm, pg[order], send, recv)
            pl = _h5._alltoallv_rows(comm, pl[order], send, recv)
        elif P > 1:
            pg, pl = _gather_rows(comm, pg), _gather_rows(comm, pl)
            if comm.rank != 0:
                pg, pl = pg[:0], pl[:0]
        order = np.lexsort((pg[:, 1], pg[:, 0]))
        pg, pl = pg[order], pl[order]
        dup = len(pg) > 1 and bool(np.any((pg[1:] == pg[:-1]).all(axis=1)))
        err = _h5.first_error(comm, f"a pair is given twice (rank {comm.rank})" if dup else None)
        if err is not None:
            raise ValueError(f"{self.path}: snapshot not written: {err}")
        start, total = _h5.exscan(comm, len(pg))
        return start, total, pg, pl

    def write(self, local_gid, fields, attrs, pairs=None):
        """Write one snapshot, collectively (every rank calls it, a rank may hold no rows).

        local_gid : (n_local,) int global ids of this rank's rows, in any order
        fields : {name: (n_local,) or (n_local, k) array} rows aligned with local_gid
            (position, diameter, pressure, contacts; any others are stored as well); the
            writer adds radius = diameter / 2
        attrs : snapshot attributes; must hold ``iteration``; rank 0's values are written
            (wall times differ between ranks)
        pairs : None, or (gid_i, gid_j, lambda) of this rank's contact pairs (int64, int64,
            float64 arrays of one length, possibly 0): each pair given by exactly one rank,
            gid_i < gid_j; stored sorted as ``pairs/gid`` and ``pairs/lambda``

        Returns this rank's wall time for the write, in seconds.
        """
        if self.closed:
            raise ValueError(f"{self.path}: write() after close()")
        t0 = time.perf_counter()
        comm = self.comm
        gid = np.ascontiguousarray(local_gid, dtype=np.int64).ravel()
        fields = self._check(gid, {k: np.asarray(v) for k, v in fields.items()})
        if self.dim == 1 and "position" in fields:
            pxy = np.zeros((len(gid), 2), dtype=fields["position"].dtype)
            pxy[:, 0] = fields["position"][:, 0]
            fields["position_xy"] = pxy
        attrs = dict(_h5.bcast(comm, dict(attrs)))
        if "iteration" not in attrs:
            raise ValueError("snapshot attrs must hold 'iteration'")
        attrs["iteration"] = int(attrs["iteration"])
        pairs = self._check_pairs(pairs)
        radius = "diameter" in fields and "radius" not in fields
        need = sum(self.n_global * int(np.prod(v.shape[1:], dtype=np.int64)) * v.dtype.itemsize
                   for v in fields.values())
        if radius:
            need += self.n_global * fields["diameter"].dtype.itemsize
        if pairs is not None:
            need += _h5.exscan(comm, len(pairs[1]))[1] * (2 * 8 + 8)
        err = _h5.space_problem(comm, self.path, need)
        if err is not None:
            raise SnapshotError(self._msg(f"snapshot {attrs['iteration']} not written: {err}"))
        if pairs is not None:
            pairs = self._sorted_pairs(*pairs)
        if self.parallel:
            if self.method == "redistribute":
                lo, data = _h5.to_gid_blocks(comm, self.n_global, gid, fields)
                where = lo
            else:
                order = np.argsort(gid, kind="stable")
                where = gid[order]
                total = comm.mpi.allreduce(len(gid))
                if total != self.n_global:
                    raise ValueError(f"{self.path}: snapshot not written: {total} rows for N = {self.n_global}")
                data = {k: _h5.take_rows(v, order) for k, v in fields.items()}
            if radius:
                data["radius"] = data["diameter"] * 0.5
            attrs["checksums"] = self._checksums(data, where, pairs)
            err = None
            try:
                if self._xfer is None:
                    self._xfer = _h5.dxpl(True)
                with _h5.open_file(comm, self.path, "r+", True) as f:
                    self._write_group(f, attrs, data, where, self._xfer, pairs)
            except Exception as e:
                err = self._msg(f"snapshot {attrs['iteration']} not written: {_h5.one_line(e)}")
        else:
            data = _h5.gather_to_root(comm, self.n_global, gid, fields)
            err = None
            if comm.rank == 0:
                if radius:
                    data["radius"] = data["diameter"] * 0.5
                attrs["checksums"] = self._checksums(data, 0, pairs, serial=True)
                try:
                    with _h5.open_file(comm, self.path, "r+", False, locking=False) as f:
                        self._write_group(f, attrs, data, 0, None, pairs)
                except Exception as e:
                    err = self._msg(f"snapshot {attrs['iteration']} not written: {_h5.one_line(e)}")
            err = _h5.bcast(comm, err)
        err = _h5.first_error(comm, err)
        if err is None and comm.rank == 0:
            entry = {"iteration": attrs["iteration"], "group": f"/snapshots/{_group_name(attrs['iteration'])}",
                     "fields": {k: ((self.n_global,) + v.shape[1:], v.dtype.str) for k, v in data.items()},
                     "pairs": pairs[1] if pairs is not None else None}
            self._entries = [e for e in self._entries if e["iteration"] != entry["iteration"]]
            self._entries.append(entry)
            self._entries.sort(key=lambda e: e["iteration"])
            try:
                self._write_xdmf()
            except OSError as e:
                err = f"{self.xdmf_path}: not written: {_h5.one_line(e)}"
        if self.xdmf_path is not None:
            err = _h5.bcast(comm, err)   # rank 0's XDMF outcome, so that all ranks raise or none
        if err is not None:
            raise SnapshotError(err)
        self.last_seconds = time.perf_counter() - t0
        return self.last_seconds

    def _checksums(self, data, where, pairs, serial=False):
        """The JSON text of every dataset's checksum (``_h5.checksum_rows``; the pairs' too),
        from the rows this rank writes: a block from row ``where`` or the rows ``where`` lists.
        Collective unless ``serial`` (rank 0 writes everything)."""
        shares = {}
        for k, v in data.items():
            shares[k] = (_h5.checksum_at(v, where) if isinstance(where, np.ndarray)
                         else _h5.checksum_rows(v, where))
        if pairs is not None:
            start, _, pg, pl = pairs
            shares["pairs/gid"] = _h5.checksum_rows(pg, start)
            shares["pairs/lambda"] = _h5.checksum_rows(pl, start)
        if serial:
            return _h5.checksums_attr(shares)
        return _h5.checksums_attr(_h5.checksum_total(self.comm, shares))

    def _write_group(self, f, attrs, data, where, xfer, pairs=None):
        """Create the snapshot group and its datasets and write this rank's rows: a block
        starting at row ``where`` (int), or the rows listed in ``where`` (array, points); and
        the pairs (first row, total, rows, lambdas) from ``_sorted_pairs``."""
        if "topology" not in f:
            lo, hi = (_h5.gid_block(self.n_global, self.comm.size, self.comm.rank)
                      if self.parallel else (0, self.n_global))
            d = _h5.create_dataset(_h5.create_group(f, "topology"), "vertex", (self.n_global,),
                                   self._topology_dtype)
            _h5.write_rows(d, lo, np.arange(lo, hi, dtype=self._topology_dtype), xfer)
        snaps = f["snapshots"]
        name = _group_name(attrs["iteration"])
        if name in snaps:
            del snaps[name]
        g = _h5.create_group(snaps, name)
        for k in sorted(data):
            v = data[k]
            d = _h5.create_dataset(g, k, (self.n_global,) + v.shape[1:], v.dtype)
            if isinstance(where, np.ndarray):
                _h5.write_points(d, where, v, xfer)
            else:
                _h5.write_rows(d, where, v, xfer)
        if pairs is not None:
            start, total, pg, pl = pairs
            p = _h5.create_group(g, "pairs")
            _h5.write_rows(_h5.create_dataset(p, "gid", (total, 2), np.int64), start, pg, xfer)
            _h5.write_rows(_h5.create_dataset(p, "lambda", (total,), np.float64), start, pl, xfer)
        _h5.set_attrs(g, attrs)

    def close(self):
        """End the series (the file itself is already closed after every snapshot)."""
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _gather_rows(comm, arr):
    """Every rank's rows of arr on rank 0 in rank order (others get their own back)."""
    counts = np.array(comm.mpi.allgather(len(arr)), dtype=np.int64)
    arr = np.ascontiguousarray(arr)
    rtype = _h5._row_type(arr)
    try:
        if comm.rank == 0:
            recv = np.empty((int(counts.sum()),) + arr.shape[1:], dtype=arr.dtype)
            comm.mpi.Gatherv([arr, len(arr), rtype], [recv, (counts, _h5._displs(counts)), rtype], root=0)
            return recv
        comm.mpi.Gatherv([arr, len(arr), rtype], None, root=0)
        return arr
    finally:
        rtype.Free()


def _snapshot_group(f, path, iteration):
    snaps = f["snapshots"]
    names = sorted(snaps)
    if not names:
        raise SnapshotError(f"{path}: holds no snapshot")
    name = names[-1] if iteration is None else _group_name(iteration)
    if name not in snaps:
        raise SnapshotError(f"{path}: no snapshot of iteration {iteration}")
    return snaps[name]


def damaged(path, attrs, totals):
    """A one-line message when datasets read do not match the checksums stored with their
    snapshot (``totals``: {name: checksum of what was read}), else None. Snapshots written before
    the checksums have none and pass."""
    stored = attrs.get("checksums")
    if stored is None:
        return None
    want = _h5.checksums_from_attr(stored)
    bad = sorted(k for k in totals if want is None or k not in want or want[k] != totals[k])
    if bad:
        return (f"{path}: damaged snapshot {attrs.get('iteration', '?')}: {', '.join(bad[:3])} "
                f"do{'es' if len(bad) == 1 else ''} not match {'its' if len(bad) == 1 else 'their'} checksum")
    return None


def check_group(path, group):
    """Raise SnapshotError (one line) when a dataset of this snapshot group (h5py.Group; its
    pairs too) does not match its stored checksum (serial; reads every dataset)."""
    h5py = _h5.h5py()
    totals = {}
    for k, d in group.items():
        if isinstance(d, h5py.Dataset):
            totals[k] = _h5.checksum_rows(d[()], 0)
    if "pairs" in group:
        totals["pairs/gid"] = _h5.checksum_rows(group["pairs/gid"][()], 0)
        totals["pairs/lambda"] = _h5.checksum_rows(group["pairs/lambda"][()], 0)
    problem = damaged(path, _h5.read_attrs(group), totals)
    if problem:
        raise SnapshotError(problem)


def read_snapshot(path, iteration=None):
    """(fields, attrs) of one snapshot, serially (tests, post-processing): iteration None means
    the last one. fields: {name: (N, ...) array in gid order} (the contact pairs: read_pairs).
    Raises SnapshotError (one line) when a dataset does not match its checksum."""
    h5py = _h5.h5py()
    with h5py.File(path, "r") as f:
        g = _snapshot_group(f, path, iteration)
        fields = {k: g[k][()] for k in g if isinstance(g[k], h5py.Dataset)}
        attrs = _h5.read_attrs(g)
    problem = damaged(path, attrs, {k: _h5.checksum_rows(v, 0) for k, v in fields.items()})
    if problem:
        raise SnapshotError(problem)
    return fields, attrs


def read_pairs(path, iteration=None):
    """(gid (M, 2) int64, lambda (M,) float64) of one snapshot's contact pairs, rows sorted by
    (gid_i, gid_j), serially; None when the snapshot does not record them. iteration None
    means the last snapshot."""
    with _h5.h5py().File(path, "r") as f:
        g = _snapshot_group(f, path, iteration)
        if "pairs" not in g:
            return None
        pg, pl = g["pairs/gid"][()].reshape(-1, 2), g["pairs/lambda"][()]
        attrs = _h5.read_attrs(g)
    problem = damaged(path, attrs, {"pairs/gid": _h5.checksum_rows(pg, 0),
                                    "pairs/lambda": _h5.checksum_rows(pl, 0)})
    if problem:
        raise SnapshotError(problem)
    return pg, pl


def list_snapshots(path):
    """Iterations of the snapshots in path, in order (serial)."""
    with _h5.h5py().File(path, "r") as f:
        return sorted(int(f["snapshots"][k].attrs["iteration"]) for k in f.get("snapshots", {}))
