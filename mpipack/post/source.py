"""Where post-processing reads a packing: a run folder, a ``snapshots.h5`` (any snapshot, by
iteration; default the last) or a ``checkpoint.h5``, each rank reading its block of global ids.

    packing = read(comm, path, iteration=None)

On P ranks, rank r reads the rows of gids [N r/P, N (r+1)/P) (collectively through MPI-IO when
h5py has it and P > 1, else each rank opens the file read-only on its own), so memory stays
O(N / P). Every problem (no such file, a foreign or truncated file, a missing dataset, a
snapshot that does not exist, data that do not match their checksum, a non-finite position, a
diameter <= 0) is a ``PostError`` with a one-line message naming the file, raised on every rank.
"""

import dataclasses
import json
import os

import numpy as np

from mpipack.errors import InputError
from mpipack.io import CHECKPOINT_FILE, SNAPSHOT_FILE, _h5
from mpipack.io.checkpoint import CheckpointError, read_checkpoint
from mpipack.io.snapshots import FORMAT as SNAPSHOT_FORMAT, _group_name, damaged

# per-sphere datasets a snapshot may hold beyond position and diameter
OPTIONAL_FIELDS = ("pressure", "contacts", "net_force", "wall_force")


class PostError(InputError):
    """A file post-processing cannot use; the message is one line naming it (exit code 2)."""


@dataclasses.dataclass
class Packing:
    """One rank's block of a packing, rows in gid order.

    n, dim      N and b of the whole packing
    gid         (m,) int64 global ids of this rank's rows (a contiguous block)
    x           (m, b) float64 centres X_i
    diam        (m,) float64 diameters d_i
    fields      {name: (m,) array}: pressure mu_i, contacts (lambda > 0), net_force |g_i| when
                the file has them
    pairs       (gid_i, gid_j, lambda) of the contact pairs (lambda > 0) whose gid_i is in this
                rank's block, gid_i < gid_j; None when the file holds no pairs
    iteration   the snapshot's (or checkpoint's) iteration
    attrs       the snapshot's attributes (W, max_overlap, kkt_residual, wall_seconds, ...)
    scene       the run's scene (dict) when the file records it, else {}
    path        the file read; kind: "snapshot" or "checkpoint"
    summary     the run folder's summary.json when there is one, else {}
    """
    n: int
    dim: int
    gid: np.ndarray
    x: np.ndarray
    diam: np.ndarray
    fields: dict
    pairs: object
    iteration: int
    attrs: dict
    scene: dict
    path: str
    kind: str
    summary: dict


def resolve(path):
    """(file, kind, run folder or None) for a run folder, a snapshots file or a checkpoint."""
    path = os.path.abspath(os.fspath(path))
    folder = None
    if os.path.isdir(path):
        folder = path
        for name, kind in ((SNAPSHOT_FILE, "snapshot"), (CHECKPOINT_FILE, "checkpoint")):
            if os.path.isfile(os.path.join(path, name)):
                return os.path.join(path, name), kind, folder
        raise PostError(f"{path}: no {SNAPSHOT_FILE} or {CHECKPOINT_FILE} in this folder")
    if not os.path.exists(path):
        raise PostError(f"{path}: no such file or folder")
    h5py = _h5.h5py()
    if not h5py.is_hdf5(path):
        raise PostError(f"{path}: not an HDF5 file (a snapshots.h5, a checkpoint.h5 or a run folder)")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
    except OSError as e:
        raise PostError(f"{path}: cannot be read: {_h5.one_line(e)}") from None
    fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
    if fmt == SNAPSHOT_FORMAT:
        kind = "snapshot"
    elif fmt == "mpipack-checkpoint":
        kind = "checkpoint"
    else:
        raise PostError(f"{path}: not an mpipack file (format {fmt!r})")
    parent = os.path.dirname(path)
    if os.path.isfile(os.path.join(parent, "summary.json")):
        folder = parent
    return path, kind, folder


def read(comm, path, iteration=None):
    """This rank's ``Packing`` of the snapshot of ``iteration`` (None: the last) in ``path``
    (a run folder, a snapshots.h5 or a checkpoint.h5). Collective."""
    err = file = kind = folder = None
    try:
        file, kind, folder = resolve(path)
    except PostError as e:
        err = str(e)
    err = _h5.first_error(comm, err)
    if err is not None:
        raise PostError(err)
    if kind == "checkpoint":
        if iteration is not None:
            raise PostError(f"{file}: a checkpoint holds one state; --iteration applies to snapshots")
        pk = _read_checkpoint(comm, file)
    else:
        pk = _read_snapshot(comm, file, iteration)
    pk.summary = _summary(folder)
    err = _h5.first_error(comm, _values_problem(pk))
    if err is not None:
        raise PostError(err)
    return pk


def _summary(folder):
    if folder is None:
        return {}
    try:
        with open(os.path.join(folder, "summary.json")) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return {}


def _values_problem(pk):
    """A one-line problem with this rank's rows, or None."""
    bad = np.flatnonzero(~np.isfinite(pk.x).all(axis=1))
    if len(bad):
        return f"{pk.path}: snapshot {pk.iteration}: position of sphere {int(pk.gid[bad[0]])} is not finite"
    bad = np.flatnonzero(~(np.isfinite(pk.diam) & (pk.diam > 0)))
    if len(bad):
        return (f"{pk.path}: snapshot {pk.iteration}: diameter of sphere {int(pk.gid[bad[0]])} is "
                f"{pk.diam[bad[0]]!r} (must be a positive number)")
    return None


def _read_snapshot(comm, path, iteration):
    """Rank r's rows of one snapshot; the header checked on rank 0 and agreed on."""
    head, err = None, None
    if comm.rank == 0:
        try:
            head = _snapshot_header(path, iteration)
        except PostError as e:
            err = str(e)
        except (OSError, KeyError, ValueError) as e:
            err = f"{path}: cannot be read: {_h5.one_line(e)}"
    err = _h5.bcast(comm, err)
    if err is not None:
        raise PostError(err)
    head = _h5.bcast(comm, head)
    n, dim, group = head["n"], head["dim"], head["group"]
    lo, hi = _h5.gid_block(n, comm.size, comm.rank)
    parallel = comm.size > 1 and _h5.h5py_has_mpi()
    data, pairs, err = {}, None, None
    try:
        with _h5.open_file(comm, path, "r", parallel, locking=False) as f:
            xfer = _h5.dxpl(parallel)
            g = f[group]
            for name in ("position", "diameter") + tuple(k for k in OPTIONAL_FIELDS if k in head["fields"]):
                data[name] = _h5.read_rows(g[name], lo, hi, xfer)
            pairs_from = 0
            if head["pairs"]:
                pairs_from, pairs = _read_pairs(g["pairs"], lo, hi, xfer)
    except (OSError, KeyError, ValueError) as e:
        err = f"{path}: snapshot {head['iteration']} cannot be read: {_h5.one_line(e)}"
    err = _h5.first_error(comm, err)
    if err is not None:
        raise PostError(err)
    shares = {k: _h5.checksum_rows(v, lo) for k, v in data.items()}
    if pairs is not None:
        shares["pairs/gid"] = _h5.checksum_rows(np.column_stack(pairs[:2]), pairs_from)
        shares["pairs/lambda"] = _h5.checksum_rows(pairs[2], pairs_from)
    err = damaged(path, head["attrs"], _h5.checksum_total(comm, shares))
    if err is not None:
        raise PostError(err)
    fields = {k: data[k] for k in OPTIONAL_FIELDS if k in data}
    return Packing(n=n, dim=dim, gid=np.arange(lo, hi, dtype=np.int64),
                   x=np.ascontiguousarray(data["position"], dtype=np.float64),
                   diam=np.ascontiguousarray(data["diameter"], dtype=np.float64), fields=fields,
                   pairs=pairs, iteration=head["iteration"], attrs=head["attrs"], scene=head["scene"],
                   path=path, kind="snapshot", summary={})


def _snapshot_header(path, iteration):
    """N, b, the chosen group, its fields and attributes, checked (rank 0, serial)."""
    with _h5.h5py().File(path, "r") as f:
        try:
            n, dim = int(f.attrs["n"]), int(f.attrs["dim"])
        except KeyError:
            raise PostError(f"{path}: no n or dim attribute (not a snapshot file, or damaged)") from None
        snaps = f.get("snapshots")
        names = sorted(snaps) if snaps is not None else []
        if not names:
            raise PostError(f"{path}: holds no snapshot")
        if iteration is None:
            name = names[-1]
        else:
            name = _group_name(iteration)
            if name not in snaps:
                its = [int(k) for k in names]
                raise PostError(f"{path}: no snapshot of iteration {iteration} "
                                f"(it holds {len(its)}: {its[0]} .. {its[-1]})")
        g = snaps[name]
        for key, shape in (("position", (n, dim)), ("diameter", (n,))):
            if key not in g:
                raise PostError(f"{path}: snapshot {int(name)} has no {key} dataset")
            if g[key].shape != shape:
                raise PostError(f"{path}: snapshot {int(name)}: {key} has shape {g[key].shape}, expected {shape}")
        fields = [k for k in OPTIONAL_FIELDS if k in g and g[k].shape == (n,)]
        pairs = "pairs" in g and "gid" in g["pairs"] and "lambda" in g["pairs"]
        attrs = _h5.read_attrs(g)
        scene = _scene(_h5.read_attrs(f))
    return {"n": n, "dim": dim, "group": f"/snapshots/{name}", "fields": fields, "pairs": pairs,
            "iteration": int(attrs.get("iteration", int(name))), "attrs": attrs, "scene": scene}


def _read_pairs(g, lo, hi, xfer):
    """(first row, (gid_i, gid_j, lambda)) of the pairs whose first gid is in [lo, hi): rows of
    ``pairs/gid`` are sorted by (gid_i, gid_j), so they are one contiguous range, found by
    bisection on the first column."""
    gid, lam = g["gid"], g["lambda"]
    m = gid.shape[0]

    def first_at_least(value):
        a, b = 0, m
        while a < b:
            c = (a + b) // 2
            if int(gid[c, 0]) < value:
                a = c + 1
            else:
                b = c
        return a

    a, b = first_at_least(lo), first_at_least(hi)
    pg = _h5.read_rows(gid, a, b, xfer) if m else np.empty((0, 2), np.int64)
    pl = _h5.read_rows(lam, a, b, xfer) if m else np.empty(0)
    return a, (pg[:, 0].astype(np.int64), pg[:, 1].astype(np.int64), pl.astype(np.float64))


def _scene(file_attrs):
    """The run's scene (a dict) from a file's attributes, {} when it records none readable."""
    scene = file_attrs.get("scene", {})
    if isinstance(scene, str):
        try:
            scene = json.loads(scene)
        except ValueError:
            return {}
    return scene if isinstance(scene, dict) else {}


def _read_checkpoint(comm, path):
    try:
        block, scalars, attrs = read_checkpoint(comm, path)
    except CheckpointError as e:
        raise PostError(str(e)) from None
    n, dim = int(attrs["n"]), int(attrs["dim"])
    m = len(block["diam"])
    gid = np.arange(block["gid_lo"], block["gid_lo"] + m, dtype=np.int64)
    owner = np.repeat(gid, block["hist_count"])
    partner = block["hist_gid"].astype(np.int64)
    keep = (owner < partner) & (block["hist_lambda"] > 0)
    scene = _scene(attrs)
    return Packing(n=n, dim=dim, gid=gid, x=np.ascontiguousarray(block["x"], dtype=np.float64),
                   diam=np.ascontiguousarray(block["diam"], dtype=np.float64), fields={},
                   pairs=(owner[keep], partner[keep], block["hist_lambda"][keep].astype(np.float64)),
                   iteration=int(scalars.get("iteration", -1)), attrs={}, scene=scene, path=path,
                   kind="checkpoint", summary={})
