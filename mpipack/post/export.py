"""A packing in the files OVITO, LAMMPS and HOOMD read: ``mpipack export RUN [--format F]``.

    export(comm, path, fmt, out=None, iteration=None) -> the written file (same on every rank)
    main(comm, args) -> exit code        args: .run, .format ("xyz"), .out, .iteration
    write_xyz(path, x, diam, fields=None, info=None)
    write_lammps_dump(path, x, diam, fields=None, timestep=0)
    write_lammps_data(path, x, diam, title=None)
    write_gsd(path, x, diam, fields=None, step=0)

``path`` is what ``post.source.read`` takes: a run folder, a snapshots.h5 (the snapshot of
``iteration``, default the last) or a checkpoint.h5. Rank 0 reads the whole packing serially and
writes the file; the other ranks wait for its outcome (the file's path, or the one-line
``PostError``). Default output, beside the snapshots: ``<run>/export/packing-<iteration>.<ext>``
(ext xyz, dump, data, gsd); ``out`` names a file, or a folder to put that name in. A run's own
files are never overwritten: an existing HDF5 file, the file read, or any existing file directly
in the folder of the file read is refused.

The writers take arrays in gid order: ``x`` (N, b) centres, b = 1, 2 or 3, ``diam`` (N,)
diameters, ``fields`` {name: (N,) or (N, k) array} per-sphere values (a packing's pressure mu_i,
contacts, net_force |g_i|). Every format has 3 coordinates: a 1D or 2D packing's are padded with
zeros (y = z = 0, or z = 0). Text formats hold every float64 at full precision (Python's repr,
the shortest text that reads back to the same bits); ids are gid + 1 everywhere (LAMMPS
numbering). The box of every format encloses every sphere with a margin of one largest diameter
dmax on each side: along axis k < b, [min_i(x_ik - r_i) - dmax, max_i(x_ik + r_i) + dmax]; along a
padded axis, [-1.5 dmax, 1.5 dmax].

Extended XYZ (``xyz``; OVITO, ASE; one frame)::

    N
    Lattice="Lx 0 0 0 Ly 0 0 0 Lz" Origin="xlo ylo zlo" Properties=species:S:1:pos:R:3:radius:R:1:
        pressure:R:1:contacts:I:1:net_force:R:1:id:I:1 pbc="F F F" iteration=K dim=b n=N source="FILE"
    X x y z r_i mu_i contacts_i |g_i| id          one line per sphere, gid order

    (the second line is one line in the file, wrapped here)

    species "X" for every sphere (ASE's dummy element; a type name to OVITO); radius r_i = d_i / 2
    (OVITO's Radius); one ``name:R:1`` (``:I:1`` for integers, ``:R:k`` for k columns) per field
    present, in the order given; the cell is the box above (Lattice rows are its edge vectors,
    Origin its lower corner), not periodic.

LAMMPS dump (``lammps-dump``; OVITO, LAMMPS ``read_dump``)::

    ITEM: TIMESTEP
    K
    ITEM: NUMBER OF ATOMS
    N
    ITEM: BOX BOUNDS ff ff ff
    xlo xhi
    ylo yhi
    zlo zhi
    ITEM: ATOMS id type x y z radius pressure contacts net_force
    id 1 x y z r_i mu_i contacts_i |g_i|        one line per sphere, gid order; the fields present

LAMMPS data file (``lammps-data``; ``atom_style sphere`` then ``read_data FILE``)::

    LAMMPS data file from mpipack: N spheres, iteration K[, 2D packing: 'dimension 2' before read_data]

    N atoms
    1 atom types

    xlo xhi xlo xhi
    ylo yhi ylo yhi
    zlo zhi zlo zhi

    Atoms # sphere

    id 1 d_i 1 x y z                            atom-ID atom-type diameter density x y z

    The density is 1 (LAMMPS derives each mass from it; ``set type 1 density`` changes it). The
    data file has no per-sphere values beyond these (use the dump for the pressure). A 2D
    packing needs ``dimension 2`` in the input script before ``read_data`` (z = 0 and the z
    bounds straddle 0, as LAMMPS requires); LAMMPS has no 1D: a 1D packing is written as a 2D
    one on the line y = 0. The box is not periodic: use ``boundary f f f`` in 3D and
    ``boundary f f p`` in 2D (LAMMPS wants a periodic z in 2D).

GSD (``gsd``; HOOMD-blue, OVITO, freud; through the ``gsd`` package, HOOMD schema, one frame)::

    configuration/step          uint64   K
    configuration/dimensions    uint8    3, or 2 for a 1D or 2D packing (GSD has no 1D)
    configuration/box           float32  [Lx, Ly, Lz, 0, 0, 0], centred on the origin (HOOMD's
                                         box is [-L/2, L/2)): L_k = 2 max(|lo_k|, |hi_k|) of the
                                         box above (rounded up to float32), so the centres are not
                                         shifted; Lz = 0 in 2D
    particles/N                 uint32   N
    particles/types, typeid              ["X"], all 0
    particles/position          float32  (N, 3): the schema's type, which HOOMD and OVITO read;
                                         rounded from float64 (relative error <= 6e-8)
    particles/diameter          float32  (N,)
    log/particles/<field>                (N,) or (N, k), the field's own dtype (pressure float64,
                                         contacts int32, net_force float64): HOOMD's per-particle
                                         log quantities, ``frame.log["particles/pressure"]``
    log/particles/position_float64, log/particles/diameter_float64
                                         the exact centres (N, 3) and diameters (N,)
"""

import os
import sys

import numpy as np

from mpipack.errors import EXIT_INPUT, EXIT_OK
from mpipack.post.source import PostError, read

FORMATS = ("xyz", "lammps-dump", "lammps-data", "gsd")
EXTENSIONS = {"xyz": "xyz", "lammps-dump": "dump", "lammps-data": "data", "gsd": "gsd"}
EXPORT_DIR = "export"        # inside the run folder
SPECIES = "X"                # every sphere's type name (xyz species, GSD type); LAMMPS type 1
ROWS_PER_CHUNK = 65536       # text rows formatted and written at a time
RESERVED = ("species", "pos", "radius", "id", "type", "x", "y", "z", "diameter", "density",
            "position_float64", "diameter_float64")  # no field may take these names


# ---- geometry shared by the formats ---------------------------------------------------------

def _checked(x, diam):
    """x padded to (N, 3) float64, diam (N,) float64, and b; ValueError on bad shapes."""
    x = np.asarray(x, dtype=np.float64)
    diam = np.asarray(diam, dtype=np.float64)
    if x.ndim != 2 or not 1 <= x.shape[1] <= 3:
        raise ValueError(f"positions must be an (N, b) array with b = 1, 2 or 3, got shape {x.shape}")
    if diam.shape != (x.shape[0],):
        raise ValueError(f"diameters must have shape ({x.shape[0]},), got {diam.shape}")
    b = x.shape[1]
    x3 = np.zeros((x.shape[0], 3), dtype=np.float64)
    x3[:, :b] = x
    return x3, diam, b


def box_bounds(x, diam):
    """(lo, hi), (3,) float64 each: the box enclosing every sphere with one largest diameter of
    margin on each side; along the axes a 1D or 2D packing pads, [-1.5 dmax, 1.5 dmax]."""
    x3, diam, b = _checked(x, diam)
    dmax = float(diam.max()) if len(diam) else 1.0
    lo = np.full(3, -1.5 * dmax)
    hi = np.full(3, 1.5 * dmax)
    if len(diam):
        r = 0.5 * diam[:, None]
        lo[:b] = (x3[:, :b] - r).min(axis=0) - dmax
        hi[:b] = (x3[:, :b] + r).max(axis=0) + dmax
    return lo, hi


def _field_columns(fields, n):
    """[(name, (N, k) array, is_integer)] of the fields, checked."""
    out = []
    for name, value in (fields or {}).items():
        a = np.asarray(value)
        if not name or any(c.isspace() or c in ':"=' for c in name):
            raise ValueError(f"field name {name!r}: no spaces, ':', '\"' or '=' allowed")
        if name in RESERVED:
            raise ValueError(f"field name {name!r} is a column every file has already")
        if a.shape[:1] != (n,) or a.ndim > 2 or a.dtype.kind not in "fiub":
            raise ValueError(f"field {name!r}: must be a numeric ({n},) or ({n}, k) array, got {a.dtype} {a.shape}")
        out.append((name, a.reshape(n, -1), a.dtype.kind in "iub"))
    return out


def _text(column, integer):
    """The column's values as text: integers in decimal, floats as Python's repr (the shortest
    text that reads back to the same float64)."""
    if integer:
        return list(map(str, np.asarray(column).astype(np.int64).tolist()))
    return list(map(repr, np.asarray(column, dtype=np.float64).tolist()))


def _write_rows(fh, n, columns):
    """One line per row: columns are callables (lo, hi) -> list of N[lo:hi] strings."""
    for lo in range(0, n, ROWS_PER_CHUNK):
        hi = min(n, lo + ROWS_PER_CHUNK)
        cols = [c(lo, hi) for c in columns]
        fh.write("\n".join(map(" ".join, zip(*cols))))
        fh.write("\n")


def _const(text):
    return lambda lo, hi: [text] * (hi - lo)


def _ids(lo, hi):
    return list(map(str, range(lo + 1, hi + 1)))


def _floats(a):
    return lambda lo, hi: _text(a[lo:hi], False)


def _field_getters(cols):
    getters = []
    for _, a, integer in cols:
        for k in range(a.shape[1]):
            getters.append(lambda lo, hi, a=a, k=k, integer=integer: _text(a[lo:hi, k], integer))
    return getters


def _quoted(text):
    """A value for an extended XYZ comment line: double quotes, none inside, one line."""
    return '"' + " ".join(str(text).split()).replace('"', "'") + '"'


# ---- the writers ----------------------------------------------------------------------------

def write_xyz(path, x, diam, fields=None, info=None):
    """Extended XYZ (layout in the module docstring); ``info`` {key: value} adds key=value pairs
    to the comment line (numbers as they are, other values quoted). Returns path."""
    x3, diam, b = _checked(x, diam)
    n = len(diam)
    cols = _field_columns(fields, n)
    lo, hi = box_bounds(x3[:, :b], diam)
    edge = hi - lo
    lattice = " ".join(repr(float(v)) for v in np.diag(edge).ravel())
    props = "species:S:1:pos:R:3:radius:R:1" + "".join(
        f":{name}:{'I' if integer else 'R'}:{a.shape[1]}" for name, a, integer in cols) + ":id:I:1"
    pairs = [f'Lattice="{lattice}"', 'Origin="' + " ".join(repr(float(v)) for v in lo) + '"',
             f"Properties={props}", 'pbc="F F F"']
    for key, value in (info or {}).items():
        if not str(key).isidentifier():
            raise ValueError(f"info key {key!r}: must be a plain name")
        if isinstance(value, np.generic):
            value = value.item()
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        pairs.append(f"{key}={value!r}" if number else f"{key}={_quoted(value)}")
    radius = 0.5 * diam
    with open(path, "w") as fh:
        fh.write(f"{n}\n{' '.join(pairs)}\n")
        _write_rows(fh, n, [_const(SPECIES), _floats(x3[:, 0]), _floats(x3[:, 1]), _floats(x3[:, 2]),
                            _floats(radius)] + _field_getters(cols) + [_ids])
    return path


def write_lammps_dump(path, x, diam, fields=None, timestep=0):
    """A LAMMPS text dump of one timestep (layout in the module docstring). Returns path."""
    x3, diam, b = _checked(x, diam)
    n = len(diam)
    cols = _field_columns(fields, n)
    lo, hi = box_bounds(x3[:, :b], diam)
    names = []
    for name, a, _ in cols:
        names += [name] if a.shape[1] == 1 else [f"{name}[{k + 1}]" for k in range(a.shape[1])]
    with open(path, "w") as fh:
        fh.write(f"ITEM: TIMESTEP\n{int(timestep)}\nITEM: NUMBER OF ATOMS\n{n}\n"
                 "ITEM: BOX BOUNDS ff ff ff\n")
        for k in range(3):
            fh.write(f"{float(lo[k])!r} {float(hi[k])!r}\n")
        fh.write("ITEM: ATOMS " + " ".join(["id", "type", "x", "y", "z", "radius"] + names) + "\n")
        _write_rows(fh, n, [_ids, _const("1"), _floats(x3[:, 0]), _floats(x3[:, 1]), _floats(x3[:, 2]),
                            _floats(0.5 * diam)] + _field_getters(cols))
    return path


def write_lammps_data(path, x, diam, title=None):
    """A LAMMPS data file for ``atom_style sphere`` (layout in the module docstring); ``title``
    is its first line (LAMMPS skips it). Returns path."""
    x3, diam, b = _checked(x, diam)
    n = len(diam)
    lo, hi = box_bounds(x3[:, :b], diam)
    if title is None:
        title = f"LAMMPS data file from mpipack: {n} spheres"
        if b < 3:
            title += ", 2D packing: 'dimension 2' before read_data"
    with open(path, "w") as fh:
        fh.write(" ".join(str(title).split()) + "\n\n")
        fh.write(f"{n} atoms\n1 atom types\n\n")
        for k, axis in enumerate("xyz"):
            fh.write(f"{float(lo[k])!r} {float(hi[k])!r} {axis}lo {axis}hi\n")
        fh.write("\nAtoms # sphere\n\n")
        _write_rows(fh, n, [_ids, _const("1"), _floats(diam), _const("1"),
                            _floats(x3[:, 0]), _floats(x3[:, 1]), _floats(x3[:, 2])])
    return path


def write_gsd(path, x, diam, fields=None, step=0):
    """A one-frame GSD file in the HOOMD schema (layout in the module docstring). Returns path."""
    import gsd.hoomd
    x3, diam, b = _checked(x, diam)
    n = len(diam)
    cols = _field_columns(fields, n)
    lo, hi = box_bounds(x3[:, :b], diam)
    length = 2.0 * np.maximum(np.abs(lo), np.abs(hi))
    length32 = length.astype(np.float32)
    length32 = np.where(length32 < length, np.nextafter(length32, np.float32(np.inf)), length32)
    frame = gsd.hoomd.Frame()
    frame.configuration.step = int(step)
    frame.configuration.dimensions = 3 if b == 3 else 2
    frame.configuration.box = np.array([length32[0], length32[1], length32[2] if b == 3 else 0.0, 0.0, 0.0, 0.0],
                                       dtype=np.float32)
    frame.particles.N = n
    frame.particles.types = [SPECIES]
    frame.particles.typeid = np.zeros(n, dtype=np.uint32)
    frame.particles.position = x3.astype(np.float32)
    frame.particles.diameter = diam.astype(np.float32)
    for name, a, _ in cols:
        frame.log[f"particles/{name}"] = np.ascontiguousarray(a[:, 0] if a.shape[1] == 1 else a)
    frame.log["particles/position_float64"] = x3
    frame.log["particles/diameter_float64"] = diam.copy()
    open(path, "w").close()  # created as any file is (the umask's mode; gsd's own is 0640)
    with gsd.hoomd.open(path, mode="w") as traj:
        traj.append(frame)
    return path


# ---- a packing to a file --------------------------------------------------------------------

def default_output(packing, fmt):
    """``<folder of the file read>/export/packing-<iteration>.<ext>``."""
    return os.path.join(os.path.dirname(packing.path), EXPORT_DIR,
                        f"packing-{packing.iteration}.{EXTENSIONS[fmt]}")


def _target(packing, fmt, out):
    """The file to write, checked: never an HDF5 file, the file read, or an existing file
    directly in the run's folder."""
    if out is None:
        target = default_output(packing, fmt)
    else:
        target = os.path.abspath(os.fspath(out))
        if os.path.isdir(target):
            target = os.path.join(target, os.path.basename(default_output(packing, fmt)))
    if os.path.lexists(target):
        if os.path.isdir(target):
            raise PostError(f"{target}: is a folder; give a file name with --out")
        if os.path.realpath(target) == os.path.realpath(packing.path) or _is_hdf5(target) or \
                os.path.realpath(os.path.dirname(target)) == os.path.realpath(os.path.dirname(packing.path)):
            raise PostError(f"{target}: refusing to overwrite a file of the run; give another --out")
    return target


def _is_hdf5(path):
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError:
        return False


def write_packing(packing, fmt, target):
    """Write a whole (serially read) ``Packing`` to ``target`` in ``fmt``, through a temporary
    file in the same folder and a rename (a failed write leaves no half file)."""
    folder = os.path.dirname(target)
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(target)}.tmp-{os.getpid()}")
    fields = packing.fields
    try:
        if fmt == "xyz":
            write_xyz(tmp, packing.x, packing.diam, fields,
                      info={"iteration": int(packing.iteration), "dim": int(packing.dim), "n": int(packing.n),
                            "source": packing.path})
        elif fmt == "lammps-dump":
            write_lammps_dump(tmp, packing.x, packing.diam, fields, timestep=packing.iteration)
        elif fmt == "lammps-data":
            title = (f"LAMMPS data file from mpipack: {packing.n} spheres, iteration {packing.iteration} "
                     f"of {packing.path}")
            if packing.dim < 3:
                title += f", {packing.dim}D packing: 'dimension 2' before read_data"
            write_lammps_data(tmp, packing.x, packing.diam, title=title)
        else:
            write_gsd(tmp, packing.x, packing.diam, fields, step=packing.iteration)
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return target


def _export(comm, path, fmt, out=None, iteration=None):
    """(written file, N, iteration) on every rank, or the same PostError on every rank."""
    from mpipack.io import _h5
    if fmt not in FORMATS:
        raise PostError(f"unknown export format {fmt!r} (one of {', '.join(FORMATS)})")
    outcome, err, bug = None, None, None
    if comm.rank == 0:
        from mpipack.parallel.comm import Comm
        target = None
        try:
            packing = read(Comm.serial(), path, iteration)
            target = _target(packing, fmt, out)
            write_packing(packing, fmt, target)
            outcome = (target, int(packing.n), int(packing.iteration))
        except PostError as e:
            err = _h5.one_line(e)
        except ImportError as e:
            err = f"--format {fmt} needs a package that is not installed: {_h5.one_line(e)}"
        except OSError as e:
            where = e.filename if e.filename else (target or path)
            err = f"{where}: cannot write: {_h5.one_line(e.strerror or e)}"
        except Exception as e:  # a bug: the other ranks must not wait for ever
            bug = e
            err = f"internal error on rank 0: {type(e).__name__}: {_h5.one_line(e)}"
    outcome, err = _h5.bcast(comm, (outcome, err))
    if bug is not None:
        raise bug
    if err is not None and err.startswith("internal error on rank 0: "):
        raise RuntimeError(err)
    if err is not None:
        raise PostError(err)
    return outcome


def export(comm, path, fmt, out=None, iteration=None):
    """Write the packing of ``path`` (snapshot ``iteration``, default the last) as ``fmt``;
    returns the written file on every rank. Collective; rank 0 reads and writes. Raises
    ``PostError`` (one line, the same on every rank) on bad input or a failed write."""
    return _export(comm, path, fmt, out, iteration)[0]


def _iteration(value):
    """--iteration as an int (None: the last snapshot), from an int or its text."""
    if value is None:
        return None
    try:
        it = int(value) if isinstance(value, (int, np.integer)) else int(str(value).strip())
    except ValueError:
        raise PostError(f"--iteration: not a whole number: {value!r}") from None
    if it < 0 or isinstance(value, bool):
        raise PostError(f"--iteration: must be a whole number >= 0, got {value!r}")
    return it


def main(comm, args):
    """``mpipack export``: args.run, args.format (default "xyz"), args.out, args.iteration.
    Rank 0 prints the one summary line; returns 0, or 2 after a one-line error on rank 0."""
    fmt = getattr(args, "format", None) or "xyz"
    try:
        iteration = _iteration(getattr(args, "iteration", None))
        target, n, it = _export(comm, args.run, fmt, getattr(args, "out", None), iteration)
    except PostError as e:
        if comm.rank == 0:
            print(f"mpipack: error: {' '.join(str(e).split())}", file=sys.stderr, flush=True)
        return EXIT_INPUT
    if comm.rank == 0:
        print(f"mpipack export: {n} spheres (iteration {it}) -> {target}", flush=True)
    return EXIT_OK


def _parser():
    import argparse
    p = argparse.ArgumentParser(prog="mpipack export", description="A packing in extended XYZ, a LAMMPS "
                                "dump or data file, or GSD, for OVITO, LAMMPS and HOOMD.")
    p.add_argument("run", help="a run folder, a snapshots.h5 or a checkpoint.h5")
    p.add_argument("--format", default="xyz", help=f"one of {', '.join(FORMATS)} (default xyz)")
    p.add_argument("--out", default=None, help="the file (or a folder) to write "
                   "(default <run>/export/packing-<iteration>.<ext>)")
    p.add_argument("--iteration", default=None, help="the snapshot's iteration (default the last)")
    return p


if __name__ == "__main__":
    from mpipack.parallel.comm import Comm
    sys.exit(main(Comm(), _parser().parse_args()))
