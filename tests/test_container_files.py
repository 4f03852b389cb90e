"""The container in a run's files: ``container.vtu`` (io/container_mesh.py) beside the snapshots.

(a) its geometry, read back with meshio: a box's 2^b corners (1D: the two ends, 2D: a closed
    outline of 4 lines, 3D: 6 quads), a cylinder's rings and discs on its radius to 1e-12 (the
    lid only with a height), a sphere's points on its radius to 1e-12; the cell field ``wall``
    numbers the walls in kernels.walls order;
(b) a run with a container writes it once (rank 0), lists it in summary.json's files, and a
    rerun with --overwrite removes it (a run without a container leaves none); the same file
    from 1 and 3 ranks;
(c) pvpython opens it, and view.py renders the run with it (ParaView optional, as in
    test_paraview.py).
"""

import json
import os
import subprocess

import numpy as np
import pytest

from conftest import describe, mpipack_run
from test_paraview import PARAVIEW, display, need, picture, pv_env, pvbatch_env  # noqa: F401 (a fixture)

from mpipack.io import container_mesh


def read(folder):
    import meshio
    m = meshio.read(os.path.join(folder, container_mesh.CONTAINER_FILE))
    cells = {}
    for block, wall in zip(m.cells, m.cell_data["wall"]):
        cells.setdefault(block.type, []).append((block.data, wall))
    return m.points, {k: (np.concatenate([c for c, _ in v]), np.concatenate([w for _, w in v]))
                      for k, v in cells.items()}


def write(tmp_path, table, dim):
    container_mesh.write(tmp_path, table, dim)
    return read(tmp_path)


# ---- (a) geometry ----------------------------------------------------------------------------------

def test_box_3d_corners_and_faces(tmp_path):
    lo, hi = [-1.0, -2.0, -3.0], [1.5, 2.0, 3.25]
    pts, cells = write(tmp_path, {"kind": "box", "lo": lo, "hi": hi}, 3)
    corners = {tuple(p) for p in pts}
    assert corners == {(x, y, z) for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])}
    quads, wall = cells["quad"]
    assert list(cells) == ["quad"] and len(quads) == 6 and sorted(wall) == list(range(6))
    for q, w in zip(quads, wall):  # wall w = axis k, side -/+: its four corners lie on that plane
        k, side = divmod(int(w), 2)
        assert np.all(pts[q, k] == (hi if side else lo)[k]), (w, pts[q])
        assert len({tuple(pts[i]) for i in q}) == 4


def test_box_2d_is_a_closed_outline_and_1d_two_points(tmp_path):
    pts, cells = write(tmp_path, {"kind": "box", "lo": [-7.0, -5.0], "hi": [7.0, 6.0]}, 2)
    assert {tuple(p) for p in pts} == {(-7, -5, 0), (7, -5, 0), (7, 6, 0), (-7, 6, 0)}
    lines, wall = cells["line"]
    assert len(lines) == 4 and sorted(wall) == [0, 1, 2, 3]
    assert sorted(np.bincount(lines.ravel())) == [2, 2, 2, 2]  # every corner ends two sides: closed
    for seg, w in zip(lines, wall):
        k, side = divmod(int(w), 2)
        assert np.all(pts[seg, k] == ([7.0, 6.0] if side else [-7.0, -5.0])[k])
    pts, cells = write(tmp_path, {"kind": "box", "lo": [-2.0], "hi": [3.0]}, 1)
    assert pts[:, 0].tolist() == [-2.0, 3.0] and list(cells) == ["vertex"]


@pytest.mark.parametrize("height", [6.0, None])
def test_cylinder_on_its_radius(tmp_path, height):
    c, R = [0.5, -1.0, 2.0], 3.3
    pts, cells = write(tmp_path, {"kind": "cylinder", "centre": c, "radius": R, "height": height}, 3)
    tri, wall = cells["triangle"]
    rho = np.hypot(pts[:, 0] - c[0], pts[:, 1] - c[1])
    on_axis = rho < 1e-12
    assert np.max(np.abs(rho[~on_axis] - R)) < 1e-12
    top = c[2] + (height if height is not None else container_mesh.OPEN_HEIGHT * R)
    assert set(np.round(pts[:, 2], 12)) == {c[2], top}
    m = container_mesh.SEGMENTS
    names = {0: "side", 1: "floor", 2: "lid"}
    counts = {names[w]: int((wall == w).sum()) for w in np.unique(wall)}
    assert counts == ({"side": 2 * m, "floor": m, "lid": m} if height is not None else {"side": 2 * m, "floor": m})
    assert np.all(pts[tri[wall == 1], 2] == c[2])
    if height is not None:
        assert np.all(pts[tri[wall == 2], 2] == top)
    # the side's triangles cover the side: their area tends to 2 pi R H (a 64-gon's perimeter)
    a, b, cc = (pts[tri[wall == 0][:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, cc - a), axis=1).sum()
    assert area == pytest.approx(2 * m * R * np.sin(np.pi / m) * (top - c[2]), rel=1e-12)


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_sphere_on_its_radius(tmp_path, dim):
    c, R = [1.0, 2.0, 3.0][:dim], 2.5
    pts, cells = write(tmp_path, {"kind": "sphere", "centre": c, "radius": R}, dim)
    r = np.sqrt(((pts[:, :dim] - np.array(c)) ** 2).sum(axis=1))
    assert np.max(np.abs(r - R)) < 1e-12 and np.all(pts[:, dim:] == 0)
    kind = {1: "vertex", 2: "line", 3: "triangle"}[dim]
    assert list(cells) == [kind]
    if dim == 3:  # a closed surface: every edge is shared by two triangles
        tri = cells["triangle"][0]
        edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
        _, count = np.unique(edges, axis=0, return_counts=True)
        assert np.all(count == 2)


def test_no_container_no_mesh():
    with pytest.raises(ValueError):
        container_mesh.mesh({"kind": "none"}, 3)


# ---- (b) a run's file ------------------------------------------------------------------------------

BOX_2D = ("dim=2", "n=60", "container.kind=box", "container.lo=[-4,-4]", "container.hi=[4,4]",
          "stop.max_iter=30")


@pytest.mark.mpi
def test_a_run_writes_it_once_and_overwrite_removes_it(tmp_path):
    proc, summary, _ = mpipack_run(1, tmp_path, sets=BOX_2D)
    out = tmp_path / "out"
    assert proc.returncode in (0, 4), describe(proc)
    assert str(out / "container.vtu") in summary["files"], summary["files"]
    pts, cells = read(out)
    assert {tuple(p) for p in pts} == {(-4, -4, 0), (4, -4, 0), (4, 4, 0), (-4, 4, 0)}
    first = (out / "container.vtu").read_bytes()
    # the same file from 3 ranks
    other = tmp_path / "np3"
    other.mkdir()
    proc, summary, _ = mpipack_run(3, other, sets=BOX_2D)
    assert proc.returncode in (0, 4), describe(proc)
    assert (other / "out" / "container.vtu").read_bytes() == first
    # a rerun without a container into the same folder: --overwrite removes it
    proc, summary, _ = mpipack_run(1, tmp_path, sets=("dim=2", "n=60", "stop.max_iter=5"), extra=("--overwrite",))
    assert proc.returncode in (0, 4), describe(proc)
    assert not (out / "container.vtu").exists()
    assert not any("container" in f for f in summary["files"])


# ---- (c) ParaView ----------------------------------------------------------------------------------

PV_READ = r'''
import json, sys
from paraview import servermanager as sm
from paraview.simple import OpenDataFile
for path in sys.argv[1:]:
    r = OpenDataFile(path)
    r.UpdatePipeline()
    d = sm.Fetch(r)
    b = d.GetBounds()
    print(json.dumps({"path": path, "points": d.GetNumberOfPoints(), "cells": d.GetNumberOfCells(),
                      "bounds": list(b), "arrays": [d.GetCellData().GetArrayName(i)
                                                    for i in range(d.GetCellData().GetNumberOfArrays())]}))
'''

CASES = {"box3": ({"kind": "box", "lo": [-1, -2, -3], "hi": [1, 2, 3]}, 3, 8, 6),
         "cyl": ({"kind": "cylinder", "centre": [0, 0, 0], "radius": 3.3, "height": 6.0}, 3, 130, 256),
         "sph2": ({"kind": "sphere", "centre": [0, 0], "radius": 2.0}, 2, 64, 64),
         "box1": ({"kind": "box", "lo": [-1], "hi": [1]}, 1, 2, 2)}


def test_pvpython_opens_it(tmp_path):
    pv = need("pvpython", PARAVIEW)
    paths = []
    for name, (table, dim, _, _) in CASES.items():
        (tmp_path / name).mkdir()
        paths.append(container_mesh.write(tmp_path / name, table, dim))
    script = tmp_path / "read.py"
    script.write_text(PV_READ)
    proc = subprocess.run([pv, str(script)] + paths, env=pv_env(), capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    seen = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(seen) == len(CASES), describe(proc)
    for s, (name, (table, dim, points, cells)) in zip(seen, CASES.items()):
        assert (s["points"], s["cells"], s["arrays"]) == (points, cells, ["wall"]), (name, s)
    assert seen[1]["bounds"] == pytest.approx([-3.3, 3.3, -3.3, 3.3, 0.0, 6.0], abs=1e-9)


@pytest.mark.mpi
@pytest.mark.parametrize("dim", [2, 3])
def test_view_py_renders_the_run_with_its_container(tmp_path, display, dim):
    pvbatch = need("pvbatch", PARAVIEW)
    sets = BOX_2D if dim == 2 else ("dim=3", "n=40", "container.kind=cylinder", "container.centre=[0,0,0]",
                                    "container.radius=2.5", "container.height=4", "stop.max_iter=30")
    proc, summary, _ = mpipack_run(1, tmp_path, sets=sets)
    assert proc.returncode in (0, 4), describe(proc)
    png = tmp_path / "view.png"
    proc = subprocess.run([pvbatch, str(tmp_path / "out" / "view.py"), "--png", str(png)],
                          env=pvbatch_env(display), capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0 and png.exists(), describe(proc)
    height, width, colours = picture(png)
    assert (width, height) == (1200, 900) and colours > 50, (width, height, colours)
