"""The file layer: snapshots (HDF5 + XDMF), VTK through meshio, checkpoints.

Parallel cases run tests/mpi_scripts/io_checks.py under ``mpirun -n 1/2/3`` with a timeout;
the files they write are checked here with serial h5py and meshio against reference data that
are functions of (N, dim, seed) only. ParaView's pvpython opens the XDMF and PVD files when it
is installed (required when MPIPACK_REQUIRE_PARAVIEW=1, as in CI).
"""

import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from conftest import MPI_SCRIPTS, REPO, describe, mpi_env, mpirun

SCRIPT = MPI_SCRIPTS / "io_checks.py"
PV_SCRIPT = MPI_SCRIPTS / "io_paraview_read.py"

_spec = importlib.util.spec_from_file_location("io_checks", SCRIPT)
W = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(W)


def run_script(n, args, cwd, timeout=240):
    return mpirun(n, [sys.executable, SCRIPT] + [str(a) for a in args], cwd=cwd, timeout=timeout)


def md5(path):
    return hashlib.md5(open(path, "rb").read()).hexdigest()


def h5():
    import h5py
    return h5py


# ---- lazy imports ------------------------------------------------------------------------------

def test_importing_io_loads_neither_h5py_nor_meshio():
    code = ("import sys, mpipack.io; bad = [m for m in ('h5py', 'meshio') if m in sys.modules]; "
            "print(bad); sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], env=mpi_env(), capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, describe(proc)


# ---- snapshots on 1, 2, 3 ranks ----------------------------------------------------------------

def check_snapshot_file(path, n, dim, n_ranks):
    with h5().File(path, "r") as f:
        a = f.attrs
        assert a["format"] == "mpipack-snapshots" and a["format_version"] == 1
        assert a["n"] == n and a["dim"] == dim and a["ranks"] == n_ranks
        assert isinstance(a["version"], str) and json.loads(a["scene"])["n"] == n
        assert json.loads(a["parameters"]) == {"alpha": 7.8e-3}
        assert np.array_equal(f["topology/vertex"][()], np.arange(n))
        assert sorted(f["snapshots"]) == [f"{it:010d}" for it in W.SNAP_ITERS]
        for it in W.SNAP_ITERS:
            g = f[f"snapshots/{it:010d}"]
            ref = W.snapshot_fields(n, dim, it)
            if dim == 1:
                ref["position_xy"] = np.column_stack([ref["position"][:, 0], np.zeros(n)])
            ref["radius"] = ref["diameter"] / 2  # added by the writer, for ParaView
            assert sorted(g) == sorted(ref)
            for k, v in ref.items():
                got = g[k][()]
                assert got.dtype == v.dtype and got.shape == v.shape, (k, got.dtype, got.shape)
                assert np.array_equal(got.view(np.uint8), v.view(np.uint8)), f"{path}: {k} at {it} differs"
            want = W.snapshot_attrs(it)
            got_attrs = {k: g.attrs[k] for k in g.attrs}
            assert set(json.loads(got_attrs.pop("checksums"))) == set(ref)  # one per dataset
            assert got_attrs == want


def check_xdmf(path, n, dim):
    root = ET.parse(path).getroot()
    series = root.find("Domain/Grid")
    assert series.get("CollectionType") == "Temporal"
    grids = series.findall("Grid")
    assert [int(g.find("Time").get("Value")) for g in grids] == list(W.SNAP_ITERS)
    for g in grids:
        assert g.find("Topology").get("NumberOfElements") == str(n)
        geo = g.find("Geometry")
        assert geo.get("GeometryType") == ("XYZ" if dim == 3 else "XY")
        names = {a.get("Name") for a in g.findall("Attribute")}
        assert names == {"diameter", "radius", "pressure", "contacts"}
        assert geo.find("DataItem").text.startswith("snapshots.h5:/snapshots/")


def check_vtk(folder, n, dim):
    import meshio
    pvd = ET.parse(os.path.join(folder, "snapshots.pvd")).getroot()
    sets = pvd.findall("Collection/DataSet")
    assert [int(s.get("timestep")) for s in sets] == list(W.SNAP_ITERS)
    for s in sets:
        it = int(s.get("timestep"))
        mesh = meshio.read(os.path.join(folder, s.get("file")))
        ref = W.snapshot_fields(n, dim, it)
        pts = np.zeros((n, 3))
        pts[:, :dim] = ref["position"]
        assert np.array_equal(mesh.points, pts)
        assert len(mesh.cells) == 1 and mesh.cells[0].type == "vertex"
        assert np.array_equal(mesh.cells[0].data.ravel(), np.arange(n))
        for k in ("diameter", "pressure", "contacts"):
            assert np.array_equal(mesh.point_data[k], ref[k]), (it, k)
            assert mesh.point_data[k].dtype == ref[k].dtype


@pytest.mark.parametrize("n_ranks", [1, 2, 3])
def test_snapshots_by_gid(tmp_path, n_ranks):
    """Rows scattered over the ranks at random (one case with rank 0 empty) land in gid order,
    bitwise; redistribution, point selection, MPI-IO on one rank and the rank-0 fallback give
    byte-identical files; a second writer appends; VTK conversion under mpirun."""
    proc = run_script(n_ranks, ["snapshots", tmp_path], cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    warnings = [l for l in proc.stderr.splitlines() if "h5py has no MPI support" in l]
    # the fallback warns once per writer (two per case), on rank 0 only, and only with >1 rank
    assert len(warnings) == (2 * len(W.SNAP_CASES) if n_ranks > 1 else 0), proc.stderr
    for case, (n, dim, _) in W.SNAP_CASES.items():
        sums = {}
        for variant in W.SNAP_VARIANTS:
            path = tmp_path / case / variant / "snapshots.h5"
            check_snapshot_file(path, n, dim, n_ranks)
            check_xdmf(tmp_path / case / variant / "snapshots.xmf", n, dim)
            sums[variant] = md5(path)
        assert len(set(sums.values())) == 1, f"{case}: files differ between ways of writing: {sums}"
        check_vtk(tmp_path / case / "auto", n, dim)


def test_snapshot_append_truncate_and_refusals(tmp_path):
    from mpipack.io import SnapshotError, SnapshotWriter, list_snapshots, read_snapshot
    comm = W.make_comm()
    n, dim = 50, 2
    path = tmp_path / "snapshots.h5"
    gid = np.arange(n)[::-1].copy()
    with SnapshotWriter(comm, path, n, dim, {"scene": "{}"}) as w:
        for it in (0, 10, 20):
            f = W.snapshot_fields(n, dim, it)
            w.write(gid, {k: v[gid] for k, v in f.items()}, W.snapshot_attrs(it))
    assert list_snapshots(path) == [0, 10, 20]
    # a viewer holding the file open does not make the next snapshot fail
    viewer = subprocess.Popen([sys.executable, "-c", "import h5py, sys, time; f = h5py.File(sys.argv[1], 'r'); "
                               "print('open', flush=True); time.sleep(60)", str(path)],
                              stdout=subprocess.PIPE, text=True, env=mpi_env())
    try:
        assert viewer.stdout.readline().strip() == "open"
        with SnapshotWriter(comm, path, n, dim, {"scene": "{}"}) as w:
            f = W.snapshot_fields(n, dim, 30)
            w.write(gid, {k: v[gid] for k, v in f.items()}, W.snapshot_attrs(30))
    finally:
        viewer.kill()
        viewer.wait()
    assert list_snapshots(path) == [0, 10, 20, 30]
    # a run restarted from the checkpoint of iteration 10 drops 20 and rewrites 10
    with SnapshotWriter(comm, path, n, dim, {"scene": "{}"}, truncate_after=10) as w:
        f = W.snapshot_fields(n, dim, 999)
        w.write(gid, {k: v[gid] for k, v in f.items()}, W.snapshot_attrs(10))
    assert list_snapshots(path) == [0, 10]
    got, attrs = read_snapshot(path, 10)
    assert np.array_equal(got["pressure"], f["pressure"]) and attrs["iteration"] == 10
    grids = ET.parse(tmp_path / "snapshots.xmf").getroot().findall("Domain/Grid/Grid")
    assert [g.find("Time").get("Value") for g in grids] == ["0", "10"]

    # another N, a foreign HDF5 file, a non-HDF5 file: refused with one line, file untouched
    with pytest.raises(SnapshotError) as e:
        SnapshotWriter(comm, path, n + 1, dim, {})
    assert "N = 50" in str(e.value) and "\n" not in str(e.value) and str(path) in str(e.value)
    foreign = tmp_path / "foreign.h5"
    with h5().File(foreign, "w") as f:
        f["data"] = np.arange(3)
    text = tmp_path / "notes.h5"
    text.write_text("my notes\n")
    for p in (foreign, text):
        before = md5(p)
        with pytest.raises(SnapshotError) as e:
            SnapshotWriter(comm, p, n, dim, {})
        assert str(p) in str(e.value) and "\n" not in str(e.value)
        assert md5(p) == before

    # rows that are not a permutation of the gids
    with SnapshotWriter(comm, tmp_path / "s2.h5", n, dim, {}) as w:
        f = W.snapshot_fields(n, dim, 0)
        bad = gid.copy()
        bad[0] = bad[1]
        with pytest.raises(ValueError):
            w.write(bad, {k: v[bad] for k, v in f.items()}, W.snapshot_attrs(0))


# ---- checkpoints -------------------------------------------------------------------------------

@pytest.mark.parametrize("writer,reader,seed,wflag,rflag", [
    (1, 3, 2, None, None),            # written on 1 rank, read on 3
    (3, 2, 3, None, "--serial"),      # written on 3 (MPI-IO), read on 2 without MPI-IO
    (2, 1, 4, "--serial", None),      # written on 2 in turn without MPI-IO, read on 1
    (2, 3, 101, None, None),          # no pair history at all (iteration 0)
])
def test_checkpoint_on_another_rank_count(tmp_path, writer, reader, seed, wflag, rflag):
    """Blocks of unequal sizes (one empty) written on `writer` ranks come back on `reader` ranks
    as the blocks [N r/P, N(r+1)/P), bitwise, with the history CSR, the extra arrays and the
    scalars (float64 bits through JSON)."""
    path = tmp_path / "checkpoint.h5"
    proc = run_script(writer, ["ckpt-write", path, seed] + ([wflag] if wflag else []), cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert not (tmp_path / ".checkpoint.h5.tmp").exists()
    proc = run_script(reader, ["ckpt-read", path, seed] + ([rflag] if rflag else []), cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert sorted(l.split(":")[0] for l in proc.stdout.splitlines() if l.startswith("OK")) == \
        [f"OK rank {r}" for r in range(reader)]
    with h5().File(path, "r") as f:
        assert f.attrs["format"] == "mpipack-checkpoint" and f.attrs["format_version"] == 1
        assert f.attrs["ranks"] == writer
        assert ("x_lin" in f["particles"]) == (seed % 2 == 0)
        assert (f["history/gid"].shape[0] == 0) == (seed >= 100)


@pytest.mark.parametrize("n_ranks", [1, 2, 3])
def test_checkpoint_survives_a_rank_killed_mid_write(tmp_path, n_ranks):
    path = tmp_path / "checkpoint.h5"
    proc = run_script(n_ranks, ["ckpt-kill", path], cwd=tmp_path)
    assert proc.returncode != 0, describe(proc)
    assert (tmp_path / "checkpoint.h5.killed").read_text().startswith(f"rank {n_ranks - 1} of {n_ranks}: SIGKILL")
    assert "the killed write returned" not in proc.stdout
    assert (tmp_path / ".checkpoint.h5.tmp").exists()      # the interrupted write's debris
    W.do_ckpt_read(W.make_comm(), str(path), 1, False)       # the previous checkpoint, intact
    # the next checkpoint overwrites the debris and is readable
    proc = run_script(n_ranks, ["ckpt-write", path, 3, "--verify"], cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert not (tmp_path / ".checkpoint.h5.tmp").exists()


@pytest.fixture(scope="module")
def bad_checkpoints(tmp_path_factory):
    """{kind: (path, words the message must contain)}."""
    from mpipack.io import SnapshotWriter
    d = tmp_path_factory.mktemp("badckpt")
    comm = W.make_comm()
    good = d / "good.h5"
    ref = W.checkpoint_reference(2)
    from mpipack.io import write_checkpoint
    write_checkpoint(comm, good, W.CKPT_N, W.CKPT_DIM, W.block_of(ref, 0, W.CKPT_N),
                     W.checkpoint_scalars(2), {"scene": "{}"})
    size = good.stat().st_size
    out = {}
    for name, keep in (("truncated-half", size // 2), ("truncated-head", 1000)):
        p = d / f"{name}.h5"
        p.write_bytes(good.read_bytes()[:keep])
        out[name] = (p, "truncated")
    p = d / "wrong-version.h5"
    shutil.copy(good, p)
    with h5().File(p, "r+") as f:
        f.attrs["format_version"] = 2
    out["wrong-version"] = (p, "format version 2")
    p = d / "no-lambda.h5"
    shutil.copy(good, p)
    with h5().File(p, "r+") as f:
        del f["history/lambda"]
    out["damaged"] = (p, "no history/lambda")
    p = d / "foreign.h5"
    with h5().File(p, "w") as f:
        f["x"] = np.zeros((3, 2))
    out["foreign-hdf5"] = (p, "not an mpipack checkpoint")
    p = d / "snap" / "snapshots.h5"
    p.parent.mkdir()
    SnapshotWriter(comm, p, 4, 2, {}).close()
    out["snapshot-file"] = (p, "format attribute 'mpipack-snapshots'")
    p = d / "notes.txt"
    p.write_text("checkpoint? no\n" * 100)
    out["text"] = (p, "not an HDF5 file")
    p = d / "empty.h5"
    p.write_bytes(b"")
    out["empty"] = (p, "empty file")
    out["missing"] = (d / "missing.h5", "no such file")
    out["folder"] = (d, "is a folder")
    return out


def test_bad_checkpoints_give_one_line_errors(bad_checkpoints):
    from mpipack.io import CheckpointError, read_checkpoint
    comm = W.make_comm()
    for kind, (path, words) in bad_checkpoints.items():
        with pytest.raises(CheckpointError) as e:
            read_checkpoint(comm, path)
        msg = str(e.value)
        assert msg.startswith(f"{path}: ") and "\n" not in msg, (kind, msg)
        assert words in msg, (kind, msg)


@pytest.mark.parametrize("n_ranks", [1, 2, 3])
def test_bad_checkpoints_same_error_on_every_rank(tmp_path, bad_checkpoints, n_ranks):
    paths = [str(p) for p, _ in bad_checkpoints.values()]
    proc = run_script(n_ranks, ["ckpt-errors"] + paths, cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    rows = [json.loads(l) for l in proc.stdout.splitlines() if l.startswith("{")]
    assert len(rows) == n_ranks * len(paths), describe(proc)
    for (path, words) in bad_checkpoints.values():
        msgs = {r["error"] for r in rows if r["path"] == str(path)}
        assert len(msgs) == 1, msgs
        msg = msgs.pop()
        assert msg is not None and words in msg and "\n" not in msg, msg


# ---- ParaView ----------------------------------------------------------------------------------

def pvpython_env():
    env = dict(os.environ)
    # ParaView runs its own Python: nothing of the venv or the repo on its paths
    for k in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP"):
        env.pop(k, None)
    venv_bin = str(REPO / ".venv" / "bin")
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if p != venv_bin)
    return env


def test_paraview_opens_xdmf_and_pvd(tmp_path):
    pv = shutil.which("pvpython", path=pvpython_env()["PATH"])
    if pv is None:
        if os.environ.get("MPIPACK_REQUIRE_PARAVIEW") == "1":
            pytest.fail("MPIPACK_REQUIRE_PARAVIEW=1 but pvpython is not on PATH "
                        "(apt-get install paraview python3-paraview)")
        pytest.skip("pvpython not installed (Debian: apt-get install paraview python3-paraview; "
                    "CI installs it and sets MPIPACK_REQUIRE_PARAVIEW=1)")
    from mpipack.io import SnapshotWriter, convert_run
    comm = W.make_comm()
    iters = (0, 50)
    cases = {"2d": (400, 2), "3d": (300, 3), "1d": (100, 1)}
    files = []
    for case, (n, dim) in cases.items():
        folder = tmp_path / case
        folder.mkdir()
        gid = np.random.default_rng(5).permutation(n)
        with SnapshotWriter(comm, folder / "snapshots.h5", n, dim, {"scene": "{}"}) as w:
            for it in iters:
                f = W.snapshot_fields(n, dim, it)
                w.write(gid, {k: v[gid] for k, v in f.items()}, W.snapshot_attrs(it))
        convert_run(comm, folder)
        files += [str(folder / "snapshots.xmf"), str(folder / "snapshots.pvd")]
    proc = subprocess.run([pv, str(PV_SCRIPT)] + files, env=pvpython_env(), capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    seen = [json.loads(l) for l in proc.stdout.splitlines() if l.startswith("{")]
    assert [s["path"] for s in seen] == files, describe(proc)
    for s in seen:
        case = os.path.basename(os.path.dirname(s["path"]))
        n, dim = cases[case]
        assert s["times"] == [float(t) for t in iters], s
        for step, it in zip(s["steps"], iters):
            ref = W.snapshot_fields(n, dim, it)
            assert step["points"] == n and step["cells"] == n, (s["path"], step)
            assert {"diameter", "pressure", "contacts"} <= set(step["arrays"]), step["arrays"]
            idx = step["sample"]
            xyz = np.zeros((len(idx), 3))
            xyz[:, :dim] = ref["position"][idx]
            assert np.array_equal(np.array(step["xyz"]), xyz), (s["path"], it, step["xyz"])
            for k in ("diameter", "pressure", "contacts"):
                assert step["values"][k] == ref[k][idx].astype(float).tolist(), (s["path"], it, k)
