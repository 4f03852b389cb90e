"""A user's start read from a file: positions and diameters (``init.kind = "file"``), or diameters
only (``particles.distribution = "file"``). Reading and checking; no numerics beyond the few
figures of the diameters the scene's checks and laws need.

Formats of a start (``read_start``), row k = global id k, b = dim:

    text (.csv, .txt, any other name)  b + 1 numbers a row, x[, y[, z]], d; separated by commas
                                       or by white space; an optional header line (its first
                                       line of data holding no number); ``#`` starts a comment;
                                       blank lines are skipped
    .npy                               an array of shape (N, b + 1), rows as above
    a run folder                       its snapshots.h5, else its checkpoint.h5
    snapshots.h5                       the last snapshot, or the one of ``iteration``
    checkpoint.h5                      its positions X^n and diameters (nothing else: a new run)

Formats of diameters (``read_diameters``): text with one number a row, or a 1-D .npy (or (N, 1)).

Every problem is a ``StartError`` whose one-line message names the file: missing, unreadable,
empty, more than ``MAX_ROWS`` rows, a row of the wrong length (its line number), a column count
that does not match the scene's dim, a number that is not finite, a diameter <= 0. Two spheres
at the same centre are allowed (the engine separates them, ``engine.initial.separate``).

What a scene records of the file (``Start.sha256``): the sha256 of the numbers read, as
little-endian float64, positions (row-major) then diameters, so that a restart notices a
changed file whatever its format; the same numbers written as CSV or .npy have the same digest.

Each process reads the whole file once (``read_start``/``read_diameters`` keep the last few in
memory, keyed by path, size and modification time): the scene's checks need every diameter at
load time, and the start takes its rows by gid from the same arrays. h5py is imported only for
an HDF5 input.
"""

import functools
import hashlib
import math
import os
from types import SimpleNamespace
from typing import NamedTuple, Optional

import numpy as np

from .names import CHECKPOINT_FILE, SNAPSHOT_FILE

MAX_ROWS = 10 ** 8  # a start of more spheres than this is refused
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_AXES = ("x", "y", "z")


class StartError(ValueError):
    """A start file that cannot be used; the message is one line naming the file."""


class Start(NamedTuple):
    """A start (or a list of diameters) as read, rows in gid order.

    x         (N, b) float64 centres, or None for diameters only
    diam      (N,) float64 diameters, all > 0 and finite
    sha256    hex digest of the numbers (module docstring)
    source    what was read, for messages and the summary (the file; the snapshot's iteration)
    extent    max |x_ik| over the rows (0 for diameters only)
    d_min, d_max, d_mean    smallest, largest and mean diameter
    radius_powers   (mean (d/2)^1, mean (d/2)^2, mean (d/2)^3) over the rows
    """
    x: Optional[np.ndarray]
    diam: np.ndarray
    sha256: str
    source: str
    extent: float
    d_min: float
    d_max: float
    d_mean: float
    radius_powers: tuple

    @property
    def rows(self):
        return int(self.diam.shape[0])


def read_start(path, dim, iteration=None):
    """The ``Start`` of a start file (positions and diameters, module docstring) for a scene of
    ``dim`` dimensions; ``iteration`` picks a snapshot of a snapshots file. Raises StartError."""
    path = _existing(path)
    return _cached(path, dim, iteration, True, _stamp(path))


def read_diameters(path):
    """The ``Start`` (x None) of a diameters file: text of one column or a 1-D .npy."""
    path = _existing(path)
    return _cached(path, 0, None, False, _stamp(path))


# ---- files ------------------------------------------------------------------------------------

def _existing(path):
    path = os.path.abspath(os.path.expanduser(os.fspath(path)))
    if not os.path.exists(path):
        raise StartError(f"{path}: no such file or folder")
    return path


def _stamp(path):
    try:
        st = os.stat(path)
    except OSError as e:
        raise StartError(f"{path}: cannot be read: {e.strerror}") from None
    return st.st_size, st.st_mtime_ns


@functools.lru_cache(maxsize=4)
def _cached(path, dim, iteration, with_positions, stamp):
    if with_positions:
        x, diam, source, where = _positions_and_diameters(path, dim, iteration)
    else:
        if iteration is not None:  # pragma: no cover - the scene's check comes first
            raise StartError(f"{path}: an iteration applies to a snapshots file")
        x, diam, source, where = None, *_diameters_only(path)
    _check_values(source, x, diam, where)
    return _summarise(x, diam, source)


def _positions_and_diameters(path, dim, iteration):
    """(x, diam, source, where): where(row) names a row in messages."""
    h5 = os.path.isdir(path) or _is_hdf5(path)
    if not h5 and iteration is not None:
        raise StartError(f"{path}: init.iteration picks a snapshot of a snapshots.h5 or a run folder, "
                         f"not a row of a {'.npy' if path.endswith('.npy') else 'text'} file")
    if h5:
        x, diam, source = _from_run(path, dim, iteration)
        return x, diam, source, _row_name
    cols = dim + 1
    names = ", ".join(_AXES[:dim] + ("d",))
    if path.endswith(".npy"):
        a = _npy(path, 2)
        if a.shape[1] != cols:
            raise StartError(f"{path}: {a.shape[1]} columns, a start in {dim}D has {cols} ({names})")
        return a[:, :dim].copy(), a[:, dim].copy(), path, _row_name
    a, where = _text(path, cols, names, f"a start in {dim}D")
    return a[:, :dim].copy(), a[:, dim].copy(), path, where


def _diameters_only(path):
    if os.path.isdir(path) or _is_hdf5(path):
        raise StartError(f"{path}: particles.file takes diameters as text (one a line) or a 1-D .npy; "
                         f"to start from a run, use init.kind = \"file\"")
    if path.endswith(".npy"):
        a = _npy(path, 1)
        return a.reshape(-1).copy(), path, _row_name
    a, where = _text(path, 1, "d", "a diameters file")
    return a[:, 0].copy(), path, where


def _row_name(row):
    return f"row {row}"


def _is_hdf5(path):
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == _HDF5_MAGIC
    except OSError as e:
        raise StartError(f"{path}: cannot be read: {e.strerror}") from None


def _npy(path, ndim):
    """A .npy's array as float64, its header (shape, type) checked before its data are read."""
    from numpy.lib import format as npy
    try:
        with open(path, "rb") as fh:
            version = npy.read_magic(fh)
            header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
            shape, _, dtype = header(fh)
    except (OSError, ValueError, EOFError) as e:
        raise StartError(f"{path}: not a readable .npy file ({_one_line(e)})") from None
    if dtype.kind not in "iuf":
        raise StartError(f"{path}: holds {dtype} data, not numbers")
    ok = (len(shape) == 2) if ndim == 2 else (len(shape) == 1 or (len(shape) == 2 and shape[1] == 1))
    if not ok:
        want = "(N, dim + 1)" if ndim == 2 else "(N,)"
        raise StartError(f"{path}: an array of shape {shape}, expected {want}")
    _check_count(path, shape[0])
    try:
        return np.asarray(np.load(path, allow_pickle=False), dtype=np.float64)
    except (OSError, ValueError, EOFError) as e:
        raise StartError(f"{path}: not a readable .npy file ({_one_line(e)})") from None


def _check_count(path, rows):
    if rows == 0:
        raise StartError(f"{path}: no rows (an empty file)")
    if rows > MAX_ROWS:
        raise StartError(f"{path}: {rows} rows, more than the {MAX_ROWS:.0e} a start may have")


# ---- text ---------------------------------------------------------------------------------------

def _split(line, comma):
    line = line.split("#", 1)[0].strip()
    if not line:
        return None
    return [f.strip() for f in line.split(",")] if comma else line.split()


def _number(text):
    try:
        float(text)
        return True
    except ValueError:
        return False


def _text(path, cols, names, what):
    """(rows (N, cols) float64, where(row) -> 'line L'), from a comma- or space-separated file."""
    header = first = None  # line indices (0-based) of the header and of the first row of data
    comma = False
    try:
        with open(path, encoding="utf-8") as fh:
            for i, line in enumerate(fh):
                stripped = line.split("#", 1)[0].strip()
                if not stripped:
                    continue
                comma = "," in stripped
                fields = _split(line, comma)
                if header is None and first is None and not any(_number(f) for f in fields):
                    header = i
                    continue
                first = i
                break
    except UnicodeDecodeError:
        raise StartError(f"{path}: not a text file (not UTF-8), not a .npy or HDF5 file") from None
    except OSError as e:
        raise StartError(f"{path}: cannot be read: {e.strerror}") from None
    if first is None:
        raise StartError(f"{path}: no rows of data (an empty file{', a header only' if header is not None else ''})")
    if len(fields) != cols:
        raise StartError(f"{path}: line {first + 1} has {len(fields)} column{'s' if len(fields) != 1 else ''}, "
                         f"{what} has {cols} ({names})")
    skip = 0 if header is None else header + 1
    try:
        a = np.loadtxt(path, delimiter="," if comma else None, comments="#", skiprows=skip,
                       ndmin=2, dtype=np.float64, encoding="utf-8")
    except (ValueError, UnicodeDecodeError) as e:
        raise StartError(_text_problem(path, skip, comma, cols, names) or
                         f"{path}: cannot be read as numbers ({_one_line(e)})") from None
    _check_count(path, a.shape[0])

    def where(row):
        return f"line {_line_of_row(path, skip, row)}"
    return a, where


def _text_problem(path, skip, comma, cols, names):
    """The first bad line of a text file, as a one-line message (None if none is found)."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for i, line in enumerate(fh):
            if i < skip:
                continue
            fields = _split(line, comma)
            if fields is None:
                continue
            if len(fields) != cols:
                return (f"{path}: line {i + 1} has {len(fields)} number{'s' if len(fields) != 1 else ''}, "
                        f"expected {cols} ({names})")
            for f in fields:
                if not _number(f):
                    return f"{path}: line {i + 1}: {f!r} is not a number"
    return None


def _line_of_row(path, skip, row):
    """The 1-based line number of data row ``row`` (for messages)."""
    k = 0
    with open(path, encoding="utf-8") as fh:
        for i, line in enumerate(fh):
            if i < skip or _split(line, False) is None:
                continue
            if k == row:
                return i + 1
            k += 1
    return "?"  # pragma: no cover


# ---- a previous run -----------------------------------------------------------------------------

def _from_run(path, dim, iteration):
    """(x, diam, source) of a run folder, a snapshots.h5 or a checkpoint.h5, through the
    readers of io.snapshots and io.checkpoint (checksums checked)."""
    if os.path.isdir(path):
        for name in (SNAPSHOT_FILE, CHECKPOINT_FILE):
            if os.path.isfile(os.path.join(path, name)):
                path = os.path.join(path, name)
                break
        else:
            raise StartError(f"{path}: a folder without {SNAPSHOT_FILE} or {CHECKPOINT_FILE} "
                             f"(not a run folder)")
        if not _is_hdf5(path):
            raise StartError(f"{path}: not an HDF5 file")
    from . import _h5
    from .checkpoint import FORMAT as CHECKPOINT_FORMAT, CheckpointError, read_checkpoint
    from .snapshots import FORMAT as SNAPSHOT_FORMAT, SnapshotError, read_snapshot
    h5py = _h5.h5py()
    try:
        with h5py.File(path, "r") as f:
            attrs = _h5.read_attrs(f)
    except OSError as e:
        raise StartError(f"{path}: cannot be read: {_one_line(e)}") from None
    fmt = attrs.get("format")
    if fmt not in (SNAPSHOT_FORMAT, CHECKPOINT_FORMAT):
        what = f"format {fmt!r}" if fmt is not None else "no format attribute"
        raise StartError(f"{path}: an HDF5 file, but not an mpipack snapshots or checkpoint file ({what})")
    try:
        n, fdim = int(attrs["n"]), int(attrs["dim"])
    except (KeyError, TypeError, ValueError):
        raise StartError(f"{path}: no n or dim attribute (damaged?)") from None
    if fdim != dim:
        raise StartError(f"{path}: a packing in {fdim}D, the scene has dim = {dim}")
    _check_count(path, n)
    if fmt == CHECKPOINT_FORMAT:
        if iteration is not None:
            raise StartError(f"{path}: a checkpoint holds one state; init.iteration picks a snapshot")
        try:
            block, scalars, _ = read_checkpoint(SimpleNamespace(rank=0, size=1), path, parallel=False)
        except CheckpointError as e:
            raise StartError(str(e)) from None
        source = f"{path} (checkpoint of iteration {scalars.get('iteration', '?')})"
        return np.asarray(block["x"], np.float64), np.asarray(block["diam"], np.float64), source
    try:
        fields, snap = read_snapshot(path, iteration)
    except SnapshotError as e:
        raise StartError(str(e)) from None
    except (OSError, KeyError, ValueError) as e:
        raise StartError(f"{path}: cannot be read: {_one_line(e)}") from None
    x, diam = fields.get("position"), fields.get("diameter")
    if x is None or diam is None or x.shape != (n, dim) or diam.shape != (n,):
        raise StartError(f"{path}: snapshot {snap.get('iteration', '?')} has no position ({n}, {dim}) "
                         f"and diameter ({n},) datasets")
    source = f"{path} (snapshot of iteration {snap.get('iteration', '?')})"
    return np.asarray(x, np.float64), np.asarray(diam, np.float64), source


# ---- checks and figures -------------------------------------------------------------------------

def _check_values(source, x, diam, where):
    if x is not None:
        bad = np.flatnonzero(~np.isfinite(x).all(axis=1))
        if len(bad):
            raise StartError(f"{source}: {where(int(bad[0]))}: a position is not a finite number")
    bad = np.flatnonzero(~np.isfinite(diam))
    if len(bad):
        raise StartError(f"{source}: {where(int(bad[0]))}: the diameter is not a finite number")
    bad = np.flatnonzero(diam <= 0)
    if len(bad):
        raise StartError(f"{source}: {where(int(bad[0]))}: diameter {float(diam[bad[0]])!r} "
                         f"(it must be positive)")


def _summarise(x, diam, source):
    h = hashlib.sha256()
    if x is not None:
        h.update(np.ascontiguousarray(x, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(diam, dtype="<f8").tobytes())
    for a in (x, diam):
        if a is not None:
            a.setflags(write=False)  # shared by every caller of the cache
    n = diam.shape[0]
    r = 0.5 * diam
    with np.errstate(over="ignore"):  # a diameter of 1e300: the scene's length check refuses it
        # exact sums (math.fsum): the same figures whatever the order or the vector width
        powers = tuple(math.fsum(r ** b) / n for b in (1, 2, 3))
    return Start(x=x, diam=diam, sha256=h.hexdigest(), source=source,
                 extent=float(np.abs(x).max()) if x is not None else 0.0,
                 d_min=float(diam.min()), d_max=float(diam.max()), d_mean=2.0 * powers[0],
                 radius_powers=powers)


def _one_line(e):
    return " ".join(str(e).split())
