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
    Attribute  every other (N,) field as a node-centred Scalar (diameter, radius, pressure,
               contacts, net_force), (N, 3) fields as Vector

The contact network is a second file, ``<stem>_contacts.xmf`` (written when some snapshot holds
pairs; snapshots without them are left out of it), one grid per such snapshot, Time = iteration:

    Topology   Polyline, M elements of 2 nodes, connectivity pairs/gid (M, 2): one line per
               pair with lambda > 0, between the two centres (M = 0: no connectivity item, the
               readers fail on an empty one)
    Geometry   the spheres' (the same position dataset)
    Attribute  lambda (M,), cell-centred (when M > 0): the force chains

A second file rather than a second grid in the same one: ParaView's default reader for .xmf
(Xdmf3ReaderS) reads a collection of two grids as two pieces of one dataset (a filter on the
spheres would also run over the network), and an XDMF Function item for the radius is skipped by
the Xdmf3 readers: the radius is a stored dataset (snapshots.py).

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


def _geometry(h5_name, dim, group, fields):
    name = "position_xy" if dim == 1 else "position"
    shape, dt = fields[name]
    kind = "XYZ" if dim == 3 else "XY"
    return (f'        <Geometry GeometryType="{kind}">'
            f'{_data_item(h5_name, f"{group}/{name}", shape, dt)}</Geometry>')


_HEAD = ['<?xml version="1.0" ?>',
         '<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>',
         '<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">',
         '  <Domain>']
_TAIL = ['    </Grid>', '  </Domain>', '</Xdmf>', '']


def render_contacts(h5_name, dim, entries):
    """The XDMF text of the contact network: one grid per entry whose ``pairs`` (M, the number
    of pairs) is not None; see the module docstring."""
    out = _HEAD + ['    <Grid Name="contacts" GridType="Collection" CollectionType="Temporal">']
    for e in entries:
        m = e.get("pairs")
        if m is None:
            continue
        g = e["group"]
        out.append(f'      <Grid Name={quoteattr("contacts" + str(e["iteration"]))} GridType="Uniform">')
        out.append(f'        <Time Value="{int(e["iteration"])}"/>')
        conn = _data_item(h5_name, f"{g}/pairs/gid", (m, 2), "<i8") if m else ""
        out.append(f'        <Topology TopologyType="Polyline" NumberOfElements="{int(m)}" '
                   f'NodesPerElement="2">{conn}</Topology>')
        out.append(_geometry(h5_name, dim, g, e["fields"]))
        if m:
            out.append('        <Attribute Name="lambda" AttributeType="Scalar" Center="Cell">'
                       f'{_data_item(h5_name, f"{g}/pairs/lambda", (m,), "<f8")}</Attribute>')
        out.append('      </Grid>')
    return "\n".join(out + _TAIL)


def contacts_path(xdmf_path):
    """``<stem>_contacts.xmf`` beside ``<stem>.xmf``."""
    return os.path.splitext(os.fspath(xdmf_path))[0] + "_contacts.xmf"


def render(h5_name, n_global, dim, entries, topology="/topology/vertex", topology_dtype="int32"):
    """The XDMF text for a snapshot file.

    h5_name: the HDF5 file name as the XDMF refers to it (relative to the XDMF file).
    entries: list of dicts, one per snapshot in time order, with ``iteration``, ``group`` (the
    HDF5 path of the snapshot group) and ``fields`` ({name: (shape, dtype)}).
    """
    out = _HEAD + ['    <Grid Name="snapshots" GridType="Collection" CollectionType="Temporal">']
    n = int(n_global)
    topo = _data_item(h5_name, topology, (n,), topology_dtype)
    for e in entries:
        g = e["group"]
        fields = e["fields"]
        out.append(f'      <Grid Name={quoteattr("it" + str(e["iteration"]))} GridType="Uniform">')
        out.append(f'        <Time Value="{int(e["iteration"])}"/>')
        out.append(f'        <Topology TopologyType="Polyvertex" NumberOfElements="{n}" '
                   f'NodesPerElement="1">{topo}</Topology>')
        out.append(_geometry(h5_name, dim, g, fields))
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
    return "\n".join(out + _TAIL)


def write(xdmf_path, h5_path, n_global, dim, entries, topology_dtype="int32"):
    """(Re)write the XDMF file for entries (see ``render``), and its contacts file
    (``contacts_path``) when an entry holds pairs; the HDF5 file is referred to by its path
    relative to the XDMF file's folder."""
    xdmf_path = os.fspath(xdmf_path)
    rel = os.path.relpath(os.fspath(h5_path), os.path.dirname(os.path.abspath(xdmf_path)))
    _h5.write_text_atomic(xdmf_path, render(rel, n_global, dim, entries,
                                            topology_dtype=topology_dtype))
    if any(e.get("pairs") is not None for e in entries):
        _h5.write_text_atomic(contacts_path(xdmf_path), render_contacts(rel, dim, entries))
    elif os.path.exists(contacts_path(xdmf_path)):  # its snapshots were truncated away
        os.remove(contacts_path(xdmf_path))
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
            fields = {k: (v.shape, v.dtype.str) for k, v in g.items() if hasattr(v, "dtype")}
            pairs = g["pairs/gid"].shape[0] if "pairs/gid" in g else None
            entries.append({"iteration": int(g.attrs["iteration"]), "group": g.name,
                            "fields": fields, "pairs": pairs})
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
