"""VTK files of a run's snapshots, through meshio: one ``.vtu`` per snapshot plus a ``.pvd``.

``convert_run(comm, run_dir)`` reads ``<run_dir>/snapshots.h5`` and writes::

    <run_dir>/vtk/snapshot_<iteration, 10 digits>.vtu   unstructured grid: N points (z = 0
                                                        in 1D/2D), N vertex cells, point data
                                                        diameter, radius, pressure, contacts
                                                        (and every other (N,) or (N, k) field)
    <run_dir>/snapshots.pvd                             the collection, timestep = iteration
    <run_dir>/vtk/contacts_<iteration>.vtu              snapshots holding pairs only: the same
                                                        N points, one line cell per contact
                                                        pair (M, possibly 0), cell data lambda
    <run_dir>/snapshots_contacts.pvd                    their collection (when there are any)
    <run_dir>/view.py                                   the ParaView script (paraview.py):
                                                        ``pvbatch view.py --vtk --png x.png``

In ParaView: open the .pvd, add a Glyph filter with Glyph Type Sphere, Radius 1, Scale Array =
radius, Scale Factor = 1, Glyph Mode "All Points", and colour by pressure (what view.py does).

Under mpirun each rank converts snapshots k with k mod P == rank, reading them with serial h5py
(read-only opens of one file by several processes are safe); rank 0 writes the .pvd.
Collective: every rank gets the same list of paths, or the same error.
"""

import os
from xml.sax.saxutils import quoteattr

import numpy as np

from . import _h5, paraview as _paraview
from .snapshots import SnapshotError, check_group
from .names import PVD_FILE, SNAPSHOT_FILE, VTK_DIR

CONTACTS_PVD_FILE = os.path.splitext(PVD_FILE)[0] + "_contacts.pvd"


def _vtu_name(iteration):
    return f"snapshot_{int(iteration):010d}.vtu"


def _contacts_vtu_name(iteration):
    return f"contacts_{int(iteration):010d}.vtu"


def write_pvd(path, entries):
    """A ParaView collection file: entries = [(time, file relative to the .pvd's folder)]."""
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             '  <Collection>']
    for t, rel in entries:
        lines.append(f'    <DataSet timestep="{t}" group="" part="0" file={quoteattr(rel)}/>')
    lines += ['  </Collection>', '</VTKFile>', '']
    _h5.write_text_atomic(path, "\n".join(lines))
    return path


def _points(group):
    pos = group["position"][()]
    points = np.zeros((pos.shape[0], 3), dtype=np.float64)
    points[:, :pos.shape[1]] = pos
    return points


def snapshot_mesh(group):
    """meshio.Mesh of one snapshot group (h5py.Group): points padded to 3 components, one
    vertex cell per point, every other field as point data (radius = diameter / 2 added for
    files written before the writer stored it)."""
    import meshio
    points = _points(group)
    n = points.shape[0]
    point_data = {}
    for k, d in group.items():
        if k in ("position", "position_xy") or not hasattr(d, "dtype"):
            continue
        v = d[()]
        if v.dtype.kind in "fiu" and v.ndim in (1, 2) and v.shape[0] == n:
            point_data[k] = v
    if "radius" not in point_data and "diameter" in point_data:
        point_data["radius"] = point_data["diameter"] * 0.5
    cells = [("vertex", np.arange(n, dtype=np.int64).reshape(-1, 1))]
    return meshio.Mesh(points, cells, point_data=point_data)


def contacts_mesh(group):
    """meshio.Mesh of one snapshot's contact network (its ``pairs`` group): the N points, one
    line cell per pair, cell data lambda."""
    import meshio
    lines = group["pairs/gid"][()].reshape(-1, 2).astype(np.int64)
    lam = group["pairs/lambda"][()].astype(np.float64)
    return meshio.Mesh(_points(group), [("line", lines)], cell_data={"lambda": [lam]})


def convert_run(comm, run_dir, out_dir=None):
    """Convert every snapshot of a run to VTU, collectively.

    run_dir : a run's output folder (holding snapshots.h5) or the snapshot file itself
    out_dir : where to write (default: the folder of the snapshot file)

    Returns the list of written paths (every snapshot .vtu, then the .pvd; the contacts files and
    view.py are not listed), the same on every rank.
    Raises FileNotFoundError / ValueError on every rank when there is nothing to convert.
    """
    run_dir = os.fspath(run_dir)
    h5_path = run_dir if os.path.isfile(run_dir) else os.path.join(run_dir, SNAPSHOT_FILE)
    out_dir = os.fspath(out_dir) if out_dir is not None else os.path.dirname(os.path.abspath(h5_path))
    iters, err = None, None
    if comm.rank == 0:
        try:
            if not os.path.exists(h5_path):
                raise FileNotFoundError(f"{h5_path}: no such file (no snapshots in {run_dir})")
            with _h5.h5py().File(h5_path, "r") as f:
                if "snapshots" not in f:
                    raise ValueError(f"{h5_path}: not an mpipack snapshot file")
                iters = sorted((int(g.attrs["iteration"]), g.name, "pairs" in g)
                               for g in f["snapshots"].values())
            os.makedirs(os.path.join(out_dir, VTK_DIR), exist_ok=True)
        except (OSError, ValueError) as e:
            msg = _h5.one_line(e)  # h5py's own messages do not name the file
            err = (type(e).__name__, msg if h5_path in msg else f"{h5_path}: unreadable snapshot file ({msg})")
    iters, err = _h5.bcast(comm, (iters, err))
    if err is not None:
        raise (FileNotFoundError if err[0] == "FileNotFoundError" else ValueError)(err[1])

    mine = iters[comm.rank::comm.size]
    err = None
    try:
        if mine:
            import meshio
            with _h5.h5py().File(h5_path, "r") as f:
                for it, gname, pairs in mine:
                    check_group(h5_path, f[gname])  # damaged data are refused, not converted
                    mesh = snapshot_mesh(f[gname])
                    meshio.write(os.path.join(out_dir, VTK_DIR, _vtu_name(it)), mesh,
                                 file_format="vtu")
                    if pairs:
                        meshio.write(os.path.join(out_dir, VTK_DIR, _contacts_vtu_name(it)),
                                     contacts_mesh(f[gname]), file_format="vtu")
    except SnapshotError as e:
        err = str(e)
    except Exception as e:
        err = f"{h5_path}: VTK conversion failed on rank {comm.rank}: {_h5.one_line(e)}"
    err = _h5.first_error(comm, err)
    if err is not None:
        raise ValueError(err)
    paths = [os.path.join(out_dir, VTK_DIR, _vtu_name(it)) for it, _, _ in iters]
    pvd = os.path.join(out_dir, PVD_FILE)
    err = None
    if comm.rank == 0:
        try:
            write_pvd(pvd, [(it, f"{VTK_DIR}/{_vtu_name(it)}") for it, _, _ in iters])
            net = [(it, f"{VTK_DIR}/{_contacts_vtu_name(it)}") for it, _, pairs in iters if pairs]
            if net:
                write_pvd(os.path.join(out_dir, CONTACTS_PVD_FILE), net)
            _paraview.write_view(out_dir, os.path.splitext(PVD_FILE)[0])
        except OSError as e:
            err = f"{e.filename or pvd}: not written: {_h5.one_line(e.strerror or e)}"
    err = _h5.bcast(comm, err)
    if err is not None:
        raise ValueError(err)
    return paths + [pvd]
