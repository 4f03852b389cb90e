"""The surface of a run's container, for ParaView: ``container.vtu`` beside the snapshots.

    <folder>/container.vtu    written once per run by rank 0 (``engine.output``) when the scene
                              has a container; view.py shows it translucent beside the spheres

The container is taken as plain values, the scene's ``container`` table (a dict with ``kind``,
``lo``, ``hi``, ``centre``, ``radius``, ``height``), not as a ``config.Container``: io imports
nothing but io. Points have 3 components (z = 0 in 1D and 2D, y = 0 in 1D).

    dim  box                     cylinder (3D only)                  sphere
    1    2 vertices lo, hi       -                                   2 vertices c -+ R
    2    4 lines (the outline)   -                                   SEGMENTS lines (a circle)
    3    6 quads                 side: 2 SEGMENTS triangles; floor   UV sphere: RINGS x SEGMENTS
                                 and lid (with height) fans of       (triangles)
                                 SEGMENTS triangles

Every point of a round wall lies on it to rounding (|p - c| = R); the cell field ``wall``
numbers the wall each cell belongs to, in ``kernels.walls.walls_of``'s row order (box: -x, +x,
-y, +y, -z, +z; cylinder: side, floor, lid; sphere: 0). An open cylinder (no ``height``) is
drawn OPEN_HEIGHT radii high, without a lid.
"""

import math
import os

import numpy as np

CONTAINER_FILE = "container.vtu"
SEGMENTS = 64        # around a cylinder, a circle, a sphere's parallels
RINGS = 32           # a sphere's parallels (latitude bands)
OPEN_HEIGHT = 2.0    # an open cylinder's drawn height, in radii


def container_path(folder):
    return os.path.join(os.fspath(folder), CONTAINER_FILE)


def _pad3(v):
    v = [float(a) for a in v]
    return v + [0.0] * (3 - len(v))


def _circle(cx, cy, z, radius, segments):
    """(segments, 3) points on a circle about (cx, cy) at height z, the first at angle 0."""
    t = 2.0 * np.pi * np.arange(segments) / segments
    return np.stack([cx + radius * np.cos(t), cy + radius * np.sin(t), np.full(segments, z)], axis=1)


def mesh(container, dim, segments=SEGMENTS, rings=RINGS):
    """(points (m, 3) float64, blocks [(cell type, (k, nodes) int64, wall index)]) of the
    container's surface; cell types are meshio's ("vertex", "line", "triangle", "quad").
    ``container``: the scene's container table (dict); kind "none": ValueError."""
    kind = container.get("kind", "none")
    if kind == "box":
        lo, hi = _pad3(container["lo"]), _pad3(container["hi"])
        if dim == 1:
            return np.array([lo, hi]), [("vertex", np.array([[0]]), 0), ("vertex", np.array([[1]]), 1)]
        if dim == 2:
            pts = np.array([[lo[0], lo[1], 0.0], [hi[0], lo[1], 0.0], [hi[0], hi[1], 0.0], [lo[0], hi[1], 0.0]])
            # walls: -x (x = lo0), +x, -y, +y
            return pts, [("line", np.array([[3, 0]]), 0), ("line", np.array([[1, 2]]), 1),
                         ("line", np.array([[0, 1]]), 2), ("line", np.array([[2, 3]]), 3)]
        corner = lambda i, j, k: [(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
        pts = np.array([corner(i, j, k) for k in (0, 1) for j in (0, 1) for i in (0, 1)])
        at = lambda i, j, k: i + 2 * j + 4 * k
        faces = [  # one quad per wall, in walls_of order: -x, +x, -y, +y, -z, +z
            [at(0, 0, 0), at(0, 0, 1), at(0, 1, 1), at(0, 1, 0)],
            [at(1, 0, 0), at(1, 1, 0), at(1, 1, 1), at(1, 0, 1)],
            [at(0, 0, 0), at(1, 0, 0), at(1, 0, 1), at(0, 0, 1)],
            [at(0, 1, 0), at(0, 1, 1), at(1, 1, 1), at(1, 1, 0)],
            [at(0, 0, 0), at(0, 1, 0), at(1, 1, 0), at(1, 0, 0)],
            [at(0, 0, 1), at(1, 0, 1), at(1, 1, 1), at(0, 1, 1)],
        ]
        return pts, [("quad", np.array([f]), w) for w, f in enumerate(faces)]
    if kind == "cylinder":
        if dim != 3:
            raise ValueError(f"a cylinder is a 3D container, not {dim}D")
        c, r = _pad3(container["centre"]), float(container["radius"])
        height = container.get("height")
        top = c[2] + (float(height) if height is not None else OPEN_HEIGHT * r)
        m = segments
        bottom_ring = _circle(c[0], c[1], c[2], r, m)
        top_ring = _circle(c[0], c[1], top, r, m)
        pts = [bottom_ring, top_ring, np.array([[c[0], c[1], c[2]]])]
        k = np.arange(m)
        nxt = (k + 1) % m
        side = np.concatenate([np.stack([k, nxt, m + nxt], axis=1), np.stack([k, m + nxt, m + k], axis=1)])
        floor = np.stack([np.full(m, 2 * m), nxt, k], axis=1)
        blocks = [("triangle", side, 0), ("triangle", floor, 1)]
        if height is not None:
            pts.append(np.array([[c[0], c[1], top]]))
            blocks.append(("triangle", np.stack([np.full(m, 2 * m + 1), m + k, m + nxt], axis=1), 2))
        return np.concatenate(pts), blocks
    if kind == "sphere":
        c, r = _pad3(container["centre"]), float(container["radius"])
        if dim == 1:
            return (np.array([[c[0] - r, 0.0, 0.0], [c[0] + r, 0.0, 0.0]]),
                    [("vertex", np.array([[0], [1]]), 0)])
        if dim == 2:
            k = np.arange(segments)
            return _circle(c[0], c[1], 0.0, r, segments), [("line", np.stack([k, (k + 1) % segments], axis=1), 0)]
        # UV sphere: the poles and rings - 1 parallels of segments points
        polar = np.pi * np.arange(1, rings) / rings
        rows = [np.array([[c[0], c[1], c[2] + r]])]
        for p in polar:
            rows.append(_circle(c[0], c[1], c[2] + r * math.cos(p), r * math.sin(p), segments))
        rows.append(np.array([[c[0], c[1], c[2] - r]]))
        pts = np.concatenate(rows)
        south = len(pts) - 1
        k = np.arange(segments)
        nxt = (k + 1) % segments
        ring = lambda q: 1 + q * segments  # first point of parallel q (0-based)
        tris = [np.stack([np.zeros(segments, np.int64), ring(0) + k, ring(0) + nxt], axis=1)]
        for q in range(rings - 2):
            a, b = ring(q), ring(q + 1)
            tris.append(np.stack([a + k, b + k, b + nxt], axis=1))
            tris.append(np.stack([a + k, b + nxt, a + nxt], axis=1))
        last = ring(rings - 2)
        tris.append(np.stack([np.full(segments, south), last + nxt, last + k], axis=1))
        return pts, [("triangle", np.concatenate(tris), 0)]
    raise ValueError(f"no container to draw (container.kind = {kind!r})")


def write(folder, container, dim):
    """Write ``<folder>/container.vtu`` (serial: call on one rank) of the scene's container
    table; returns its path. OSError when the folder is not writable."""
    import meshio
    pts, blocks = mesh(container, dim)
    cells = [(kind, np.asarray(conn, dtype=np.int64)) for kind, conn, _ in blocks]
    wall = [np.full(len(conn), w, dtype=np.int64) for _, conn, w in blocks]
    path = container_path(folder)
    tmp = path + f".tmp{os.getpid()}.vtu"
    meshio.write(tmp, meshio.Mesh(np.ascontiguousarray(pts, dtype=np.float64), cells,
                                  cell_data={"wall": wall}), file_format="vtu")
    os.replace(tmp, path)
    return path
