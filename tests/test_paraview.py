"""What ParaView shows of a run: the radius, the start as the first snapshot, the contact network
(pairs with lambda > 0 as lines, lambda per line), and view.py, which renders them.

(a) the writer on 1, 2, 3 ranks (rows and pairs scattered at random, one rank empty, every way of
    writing) stores the same radius and pairs, sorted by (gid_i, gid_j); real runs on 1, 2, 3
    ranks write iteration 0 first, the same on any number of ranks; a restart keeps it;
(b) pvpython opens both XDMF files and sees radius, pressure, and the contacts with lambda;
(c) ``pvbatch view.py --png x.png`` on a virtual display (Xvfb, what ``xvfb-run -a`` gives a
    user) renders a picture that is not blank (1200 x 900, more than 50 colours), in 1D, 2D,
    3D, from the XDMF and the VTK files.

This file is also the MPI worker of (a): ``mpirun -n P python test_paraview.py write OUT``.
ParaView (pvpython, pvbatch) and Xvfb are required when MPIPACK_REQUIRE_PARAVIEW=1 (CI),
else their tests are skipped.
"""

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from conftest import MPI_SCRIPTS, describe, mpipack_run, mpirun

_spec = importlib.util.spec_from_file_location("io_checks", MPI_SCRIPTS / "io_checks.py")
W = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(W)

CASES = {"2d": (400, 2, None), "3d-empty0": (300, 3, 0), "1d": (100, 1, None)}  # N, dim, empty rank
ITERS = (0, 50, 100)
VARIANTS = {"auto": {}, "points": {"method": "points"}, "serial": {"parallel": False}}


def reference_pairs(n, dim, iteration):
    """(gid (M, 2) sorted, lambda (M,)): distinct random pairs gid_i < gid_j; none at 0."""
    if iteration == 0:
        return np.empty((0, 2), np.int64), np.empty(0)
    rng = np.random.default_rng([7, n, dim, iteration])
    g = rng.integers(0, n, size=(4 * n, 2))
    g = np.unique(np.sort(g[g[:, 0] != g[:, 1]], axis=1), axis=0)  # sorted rows, (i, j) order
    return g.astype(np.int64), rng.exponential(size=len(g))


def my_pairs(n, dim, iteration, size, rank, empty):
    """This rank's share of the reference pairs: a random cut of a random order."""
    g, lam = reference_pairs(n, dim, iteration)
    rng = np.random.default_rng([8, n, size, iteration])
    order = rng.permutation(len(g))
    owner = rng.integers(0, size, len(g))
    if empty is not None and size > 1:
        owner[owner == empty] = (empty + 1) % size
    mine = order[owner[order] == rank]
    return g[mine, 0], g[mine, 1], lam[mine]


def do_write(out):
    from mpipack.io import SnapshotWriter, convert_run
    comm = W.make_comm()
    for case, (n, dim, empty) in CASES.items():
        mine = W.scatter_gids(n, comm.size, seed=3, empty=empty)[comm.rank]
        for variant, kw in VARIANTS.items():
            path = os.path.join(out, case, variant, "snapshots.h5")
            if comm.rank == 0:
                os.makedirs(os.path.dirname(path), exist_ok=True)
            comm.mpi.Barrier()
            for its in (ITERS[:2], ITERS[2:]):  # a second writer appends (a continued run)
                with SnapshotWriter(comm, path, n, dim, {"scene": "{}"}, **kw) as w:
                    for it in its:
                        f = W.snapshot_fields(n, dim, it)
                        w.write(mine, {k: v[mine] for k, v in f.items()}, W.snapshot_attrs(it),
                                pairs=my_pairs(n, dim, it, comm.size, comm.rank, empty))
        convert_run(comm, os.path.join(out, case, "auto"))


def datasets(path):
    """{HDF5 path: bytes} of every dataset in a file."""
    import h5py
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()].tobytes())
                     if isinstance(obj, h5py.Dataset) else None)
    return out


# ---- (a) the files -------------------------------------------------------------------------------

@pytest.mark.mpi
def test_radius_start_and_pairs_the_same_on_1_2_3_ranks(tmp_path):
    from mpipack.io.snapshots import list_snapshots, read_pairs, read_snapshot
    files = {}
    for P in (1, 2, 3):
        proc = mpirun(P, [sys.executable, __file__, "write", tmp_path / f"p{P}"], cwd=tmp_path, timeout=240)
        assert proc.returncode == 0, describe(proc)
        for case, (n, dim, _) in CASES.items():
            for variant in VARIANTS:
                path = tmp_path / f"p{P}" / case / variant / "snapshots.h5"
                assert list_snapshots(path) == list(ITERS)
                for it in ITERS:
                    fields, _ = read_snapshot(path, it)
                    assert np.array_equal(fields["radius"], W.snapshot_fields(n, dim, it)["diameter"] / 2)
                    g, lam = read_pairs(path, it)
                    rg, rl = reference_pairs(n, dim, it)
                    assert g.dtype == np.int64 and lam.dtype == np.float64 and g.shape == (len(rl), 2)
                    assert np.array_equal(g, rg) and np.array_equal(lam, rl), (P, case, variant, it)
                files[P, case, variant] = datasets(path)
    for key, content in files.items():
        assert content == files[1, key[1], "auto"], f"{key}: datasets differ from 1 rank's"
    # the XDMF files: radius among the spheres' arrays; one contacts grid per snapshot
    n, dim, _ = CASES["2d"]
    folder = tmp_path / "p3" / "2d" / "auto"
    grid = ET.parse(folder / "snapshots.xmf").getroot().find("Domain/Grid/Grid")
    assert "radius" in {a.get("Name") for a in grid.findall("Attribute")}
    grids = ET.parse(folder / "snapshots_contacts.xmf").getroot().findall("Domain/Grid/Grid")
    assert [int(g.find("Time").get("Value")) for g in grids] == list(ITERS)
    for g, it in zip(grids, ITERS):
        top = g.find("Topology")
        assert top.get("TopologyType") == "Polyline" and top.get("NodesPerElement") == "2"
        assert int(top.get("NumberOfElements")) == len(reference_pairs(n, dim, it)[1])
        assert [a.get("Name") for a in g.findall("Attribute")] == (["lambda"] if it else [])
    # mpipack vtk: the contacts series, and view.py
    import meshio
    sets = ET.parse(folder / "snapshots_contacts.pvd").getroot().findall("Collection/DataSet")
    assert [int(s.get("timestep")) for s in sets] == list(ITERS)
    mesh = meshio.read(folder / sets[-1].get("file"))
    rg, rl = reference_pairs(n, dim, ITERS[-1])
    assert np.array_equal(mesh.cells[0].data, rg) and np.array_equal(mesh.cell_data["lambda"][0], rl)
    assert np.array_equal(meshio.read(folder / "vtk" / "snapshot_0000000100.vtu").point_data["radius"],
                          W.snapshot_fields(n, dim, 100)["diameter"] / 2)
    assert (folder / "view.py").read_text().startswith('"""ParaView view of an mpipack run')


def test_bad_pairs_are_refused_with_one_line(tmp_path):
    from mpipack.io import SnapshotWriter
    comm = W.make_comm()
    n, dim = 20, 2
    f = W.snapshot_fields(n, dim, 0)
    gid = np.arange(n)
    with SnapshotWriter(comm, tmp_path / "snapshots.h5", n, dim, {}) as w:
        for pairs, words in ((([3], [2], [1.0]), "gid_i < gid_j"), (([1], [20], [1.0]), "gid_i < gid_j"),
                             (([1, 1], [2, 2], [1.0, 2.0]), "twice"), (([1], [2, 3], [1.0]), "rows")):
            with pytest.raises(ValueError) as e:
                w.write(gid, f, {"iteration": 0}, pairs=pairs)
            assert words in str(e.value) and "\n" not in str(e.value) and str(tmp_path) in str(e.value)


RUN_SETS = ["n=60", "stop.max_iter=200", "output.snapshot_every=100"]


@pytest.mark.mpi
def test_runs_write_the_start_first_the_same_on_1_2_3_ranks_and_a_restart_keeps_it(tmp_path):
    from mpipack.io.snapshots import list_snapshots, read_pairs, read_snapshot
    got = {}
    for P in (1, 2, 3):
        work = tmp_path / f"p{P}"
        work.mkdir()
        sets = RUN_SETS + (["output.checkpoint_every=100"] if P == 2 else [])
        proc, summary, _ = mpipack_run(P, work, None, sets, timeout=300)
        assert summary is not None and summary["iterations"] == 200, describe(proc)
        path = work / "out" / "snapshots.h5"
        assert list_snapshots(path) == [0, 100, 200], describe(proc)
        start, attrs = read_snapshot(path, 0)
        assert attrs["iteration"] == 0 and np.array_equal(start["radius"], start["diameter"] / 2)
        got[P] = (start, read_pairs(path, 0), read_pairs(path, 200))
        assert (work / "out" / "view.py").exists() and (work / "out" / "snapshots_contacts.xmf").exists()
        # every pair once: the pressure is the sum of its spheres' lambdas
        (g, lam), end = got[P][2], read_snapshot(path, 200)[0]
        assert len(lam) > 0 and np.all(lam > 0) and np.all(g[:, 0] < g[:, 1])
        pressure = np.zeros(60)
        np.add.at(pressure, g[:, 0], lam)
        np.add.at(pressure, g[:, 1], lam)
        assert np.allclose(pressure, end["pressure"], rtol=1e-12, atol=0)
    for P in (2, 3):
        for k, v in got[1][0].items():
            assert np.array_equal(got[P][0][k], v), f"snapshot 0's {k} on {P} ranks differs"
        for a, b in zip(got[P][1:], got[1][1:]):
            assert all(np.array_equal(x, y) for x, y in zip(a, b)), f"pairs on {P} ranks differ"
    # a restart from the checkpoint of 200 continues the file: iteration 0 is kept, not rewritten
    work = tmp_path / "p2"
    before = datasets(work / "out" / "snapshots.h5")
    attrs0 = json.dumps(read_snapshot(work / "out" / "snapshots.h5", 0)[1], sort_keys=True)
    proc, summary, _ = mpipack_run(2, work, None, ["stop.max_iter=300"],
                                   extra=["--restart", work / "out"], timeout=300)
    assert summary is not None and summary["iterations"] == 300, describe(proc)
    path = work / "out" / "snapshots.h5"
    assert list_snapshots(path) == [0, 100, 200, 300]
    after = datasets(path)
    assert {k: v for k, v in after.items() if "/0000000000/" in k} == \
        {k: v for k, v in before.items() if "/0000000000/" in k}
    assert json.dumps(read_snapshot(path, 0)[1], sort_keys=True) == attrs0


def test_no_snapshots_no_files(tmp_path):
    proc, summary, _ = mpipack_run(1, tmp_path, None, ["n=30", "stop.max_iter=20", "output.snapshots=false"])
    assert summary is not None, describe(proc)
    assert not [p.name for p in (tmp_path / "out").iterdir() if p.name.startswith(("snapshots", "view"))]


# ---- (b), (c) ParaView ---------------------------------------------------------------------------

def pv_env():
    env = dict(os.environ)
    # ParaView runs its own Python: nothing of the venv or the repo on its paths
    for k in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP"):
        env.pop(k, None)
    venv = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), ".venv", "bin")
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if p != venv)
    return env


def need(program, install):
    path = shutil.which(program, path=pv_env()["PATH"])
    if path is None:
        if os.environ.get("MPIPACK_REQUIRE_PARAVIEW") == "1":
            pytest.fail(f"MPIPACK_REQUIRE_PARAVIEW=1 but {program} is not on PATH ({install})")
        pytest.skip(f"{program} not installed (Debian: {install}; CI installs it and sets "
                    "MPIPACK_REQUIRE_PARAVIEW=1)")
    return path


PARAVIEW = "apt-get install paraview python3-paraview"


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Snapshot folders of each case written on one rank, with pairs, and their VTK files."""
    from mpipack.io import SnapshotWriter, convert_run
    comm = W.make_comm()
    root = tmp_path_factory.mktemp("pv")
    out = {}
    for case, (n, dim, _) in CASES.items():
        folder = root / case
        folder.mkdir()
        gid = np.random.default_rng(5).permutation(n)
        with SnapshotWriter(comm, folder / "snapshots.h5", n, dim, {"scene": "{}"}) as w:
            for it in ITERS:
                f = W.snapshot_fields(n, dim, it)
                w.write(gid, {k: v[gid] for k, v in f.items()}, W.snapshot_attrs(it),
                        pairs=tuple(reference_pairs(n, dim, it)[0].T) + (reference_pairs(n, dim, it)[1],))
        convert_run(comm, folder)
        out[case] = folder
    return out


PV_READ = r'''
import json, sys
from paraview import servermanager as sm
from paraview.simple import OpenDataFile, XDMFReader

def leaf(d):
    while d is not None and (d.IsA("vtkMultiBlockDataSet") or d.IsA("vtkMultiPieceDataSet")):
        d = d.GetBlock(0) if d.IsA("vtkMultiBlockDataSet") else d.GetPiece(0)
    return d

for path in sys.argv[1:]:
    for reader in ("default", "XDMFReader"):
        r = OpenDataFile(path) if reader == "default" else XDMFReader(FileNames=[path])
        t = list(r.TimestepValues)
        r.UpdatePipeline(t[-1])
        d = leaf(sm.Fetch(r))
        pd, cd = d.GetPointData(), d.GetCellData()
        lam = cd.GetArray("lambda")
        rad = pd.GetArray("radius")
        print(json.dumps({"path": path, "reader": r.GetXMLName(), "times": t, "points": d.GetNumberOfPoints(),
                          "cells": d.GetNumberOfCells(),
                          "point_arrays": [pd.GetArrayName(i) for i in range(pd.GetNumberOfArrays())],
                          "cell_arrays": [cd.GetArrayName(i) for i in range(cd.GetNumberOfArrays())],
                          "lambda": [lam.GetValue(i) for i in range(3)] if lam else None,
                          "radius": [rad.GetValue(i) for i in range(3)] if rad else None,
                          "line0": [d.GetCell(0).GetPointId(k) for k in range(2)] if lam else None}), flush=True)
'''


def test_pvpython_sees_radius_pressure_and_the_contacts_with_lambda(written, tmp_path):
    pv = need("pvpython", PARAVIEW)
    script = tmp_path / "read.py"
    script.write_text(PV_READ)
    files = [str(written[c] / name) for c in CASES for name in ("snapshots.xmf", "snapshots_contacts.xmf")]
    proc = subprocess.run([pv, str(script)] + files, env=pv_env(), capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    seen = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    assert len(seen) == 2 * len(files), describe(proc)
    last = ITERS[-1]
    for s in seen:
        case = os.path.basename(os.path.dirname(s["path"]))
        n, dim, _ = CASES[case]
        assert s["times"] == [float(t) for t in ITERS], s
        assert s["points"] == n, s
        if s["path"].endswith("_contacts.xmf"):
            g, lam = reference_pairs(n, dim, last)
            assert s["cells"] == len(lam) and s["cell_arrays"] == ["lambda"], s
            assert s["lambda"] == lam[:3].tolist() and s["line0"] == g[0].tolist(), s
        else:
            assert {"radius", "pressure", "diameter"} <= set(s["point_arrays"]), s
            assert s["radius"] == (W.snapshot_fields(n, dim, last)["diameter"][:3] / 2).tolist(), s


def picture(path):
    """(height, width, distinct colours) of a PNG."""
    import matplotlib.image
    img = matplotlib.image.imread(str(path))
    rgb = (img[..., :3] * 255).round().astype(np.uint8).reshape(-1, 3)
    return img.shape[0], img.shape[1], len(np.unique(rgb, axis=0))


@pytest.fixture(scope="module")
def display():
    """A virtual X display of this module's own for pvbatch: Xvfb on a free display number,
    used once it accepts a connection on its socket. (xvfb-run -a failed about one run in three
    here with "bad X server connection" when the machine was busy.)"""
    import socket
    import time
    xvfb = need("Xvfb", "apt-get install xvfb")
    first = 100 + os.getpid() % 800
    for n in range(first, first + 50):
        sock = f"/tmp/.X11-unix/X{n}"
        if os.path.exists(f"/tmp/.X{n}-lock") or os.path.exists(sock):
            continue
        proc = subprocess.Popen([xvfb, f":{n}", "-screen", "0", "1280x1024x24", "-nolisten", "tcp", "-ac",
                                 "-noreset"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline, ready = time.monotonic() + 30, False
        while not ready and proc.poll() is None and time.monotonic() < deadline:
            try:
                with socket.socket(socket.AF_UNIX) as c:
                    c.connect(sock)
                ready = True
            except OSError:
                time.sleep(0.1)
        if ready:
            try:
                yield f":{n}"
            finally:
                proc.terminate()
                proc.wait(timeout=30)
            return
        proc.kill()
        proc.wait(timeout=30)
    pytest.fail(f"no Xvfb display could be started on :{first} .. :{first + 49}")


def pvbatch_env(display):
    return {**pv_env(), "DISPLAY": display}


@pytest.mark.parametrize("case,flags", [("2d", []), ("3d-empty0", []), ("1d", []), ("2d", ["--vtk"]),
                                        ("3d-empty0", ["--iteration", "0"])])
def test_view_py_renders_a_picture(written, display, tmp_path, case, flags):
    pvbatch = need("pvbatch", PARAVIEW)
    png = tmp_path / "view.png"
    proc = subprocess.run([pvbatch, str(written[case] / "view.py"), "--png", str(png)] + flags,
                          env=pvbatch_env(display), capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0 and png.exists(), describe(proc)
    it = flags[-1] if "--iteration" in flags else str(ITERS[-1])
    assert f"view.py: iteration {it} -> {png}" in proc.stdout, describe(proc)
    height, width, colours = picture(png)
    assert (width, height) == (1200, 900) and colours > 50, (width, height, colours)


def test_view_py_names_a_missing_iteration(written, display, tmp_path):
    pvbatch = need("pvbatch", PARAVIEW)
    proc = subprocess.run([pvbatch, str(written["2d"] / "view.py"), "--iteration", "7"],
                          env=pvbatch_env(display), capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode != 0 and "no snapshot of iteration 7" in proc.stderr, describe(proc)


if __name__ == "__main__":
    if sys.argv[1:2] == ["write"]:
        try:
            do_write(sys.argv[2])
        except BaseException:
            import traceback
            traceback.print_exc()
            sys.stderr.flush()
            from mpi4py import MPI
            MPI.COMM_WORLD.Abort(1)  # one failing rank must not leave the others waiting
