"""XDMF description of a snapshot file, so that ParaView opens the time series directly.

The XDMF file is light XML beside the ``.h5`` (same stem, ``.xmf``); every number stays in the
HDF5 file and is referenced as ``snapshots.h5:/snapshots/<it>/<field>``, relative to the XDMF
file. One temporal collection, one uniform grid per snapshot, Time = iteration:

    Topology   Polyvertex, N elements of 1 node, connectivity /topology/vertex (0..N-1, shared
               by every snapshot: without it ParaView's Xdmf3 readers make points but no cells,
               and a grid without cells shows nothing in the Points representation)
    Geometry   3D: XYZ from position (N, 3); 2D: XY from position (N, 2) (the readers set z = 0);
               1D: XY from position_xy (N, 2), stored by the writer for 1D runs only, because
               the Xdmf3 readers read neither X_Y_Z nor Function items that could pad (N, 1)
    Attribute  every other (N,) field as a node-centred Scalar (diameter, pressure, contacts),
               (N, 3) fields as Vector

Checked with ParaView 5.11 (Debian): ``Xdmf3ReaderS`` (what ``OpenDataFile`` picks),
``Xdmf3ReaderT`` and the older ``XDMFReader`` read the points, cells and arrays. Open the file by
an absolute path in pvpython: with a bare file name the Xdmf3 reader builds the HDF5 path
wrongly (it prefixes the XDMF file's own name).

Written by rank 0 only, through a temporary file and a rename, so a reader never sees half a
file.
"""

import os
from xml.sax.saxutils import escape, quoteattr

import numpy as np

from . import _h5

_TYPES = {"f": "Float", "i": "Int", "u": "UInt"}


def _data_item(h5_name, dataset, shape, dtype):
    dt = np.dtype(dtype)
    dims = " ".join(str(int(s)) for s in shape)
    ntype = "UChar" if (dt.kind == "u" and dt.itemsize == 1) else _TYPES[dt.kind]
    return (f'<DataItem Dimensions="{dims}" NumberType="{ntype}" Precision="{dt.itemsize}" '
            f'Format="HDF">{escape(h5_name)}:{escape(dataset)}</DataItem>')


def render(h5_name, n_global, dim, entries, topology="/topology/vertex", topology_dtype="int32"):
    """The XDMF text for a snapshot file.

    h5_name: the HDF5 file name as the XDMF refers to it (relative to the XDMF file).
    entries: list of dicts, one per snapshot in time order, with ``iteration``, ``group`` (the
    HDF5 path of the snapshot group) and ``fields`` ({name: (shape, dtype)}).
    """
    out = ['<?xml version="1.0" ?>',
           '<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>',
           '<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">',
           '  <Domain>',
           '    <Grid Name="snapshots" GridType="Collection" CollectionType="Temporal">']
    n = int(n_global)
    topo = _data_item(h5_name, topology, (n,), topology_dtype)
    for e in entries:
        g = e["group"]
        fields = e["fields"]
        out.append(f'      <Grid Name={quoteattr("it" + str(e["iteration"]))} GridType="Uniform">')
        out.append(f'        <Time Value="{int(e["iteration"])}"/>')
        out.append(f'        <Topology TopologyType="Polyvertex" NumberOfElements="{n}" '
                   f'NodesPerElement="1">{topo}</Topology>')
        if dim == 3:
            shape, dt = fields["position"]
            geo = ("XYZ", _data_item(h5_name, f"{g}/position", shape, dt))
        elif dim == 2:
            shape, dt = fields["position"]
            geo = ("XY", _data_item(h5_name, f"{g}/position", shape, dt))
        else:
            shape, dt = fields["position_xy"]
            geo = ("XY", _data_item(h5_name, f"{g}/position_xy", shape, dt))
        out.append(f'        <Geometry GeometryType="{geo[0]}">{geo[1]}</Geometry>')
        for name in sorted(fields):
            if name in ("position", "position_xy"):
                continue
            shape, dt = fields[name]
            if np.dtype(dt).kind not in "fiu":
                continue
            if len(shape) == 1:
                kind = "Scalar"
            elif len(shape) == 2 and shape[1] == 3:
                kind = "Vector"
            else:
                continue  # no XDMF attribute type fits; the data stays in the HDF5 file
            out.append(f'        <Attribute Name={quoteattr(name)} AttributeType="{kind}" Center="Node">'
                       f'{_data_item(h5_name, f"{g}/{name}", shape, dt)}</Attribute>')
        out.append('      </Grid>')
    out += ['    </Grid>', '  </Domain>', '</Xdmf>', '']
    return "\n".join(out)


def write(xdmf_path, h5_path, n_global, dim, entries, topology_dtype="int32"):
    """(Re)write the XDMF file for entries (see ``render``); the HDF5 file is referred to by
    its path relative to the XDMF file's folder."""
    xdmf_path = os.fspath(xdmf_path)
    rel = os.path.relpath(os.fspath(h5_path), os.path.dirname(os.path.abspath(xdmf_path)))
    _h5.write_text_atomic(xdmf_path, render(rel, n_global, dim, entries,
                                            topology_dtype=topology_dtype))
    return xdmf_path


def scan(h5_file):
    """(n_global, dim, entries, topology dtype) of an open snapshot file (h5py.File)."""
    n = int(h5_file.attrs["n"])
    dim = int(h5_file.attrs["dim"])
    entries = []
    snaps = h5_file.get("snapshots")
    if snaps is not None:
        for name in snaps:
            g = snaps[name]
            fields = {k: (g[k].shape, g[k].dtype.str) for k in g}
            entries.append({"iteration": int(g.attrs["iteration"]), "group": g.name,
                            "fields": fields})
    entries.sort(key=lambda e: e["iteration"])
    topo = h5_file.get("topology/vertex")
    return n, dim, entries, (topo.dtype.str if topo is not None else "int32")


def write_for(h5_path, xdmf_path=None):
    """Write the XDMF file describing every snapshot now in h5_path (serial; call on one rank).
    Default xdmf_path: h5_path with the suffix ``.xmf``."""
    h5_path = os.fspath(h5_path)
    if xdmf_path is None:
        xdmf_path = os.path.splitext(h5_path)[0] + ".xmf"
    with _h5.h5py().File(h5_path, "r") as f:
        n, dim, entries, tdt = scan(f)
    return write(xdmf_path, h5_path, n, dim, entries, topology_dtype=tdt)
