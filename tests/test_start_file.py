"""Starts and diameters from users' files (``init.kind = "file"``, ``particles.distribution =
"file"``, ``mpipack/io/start.py``): text and .npy round trips, n from the file, a run from a
file the same on 1, 2 and 3 ranks, a run from a previous run's snapshots (file and folder) and
checkpoint, a diameters file of N rows and of fewer, and every bad file refused in one line with
exit code 2 by ``mpipack run`` and ``mpipack check``."""

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import assert_bitwise_equal, describe, mpi_env
from mpipack import config
from mpipack.engine import initial

FILE_START = ['init.kind="file"']
# short runs: a start of a few hundred spheres and a few hundred iterations
SHORT = ["stop.rule=eps", "stop.eps=0", "stop.max_iter=200", "output.progress_every=0"]


def cli(args, cwd, timeout=300):
    return subprocess.run([sys.executable, "-m", "mpipack.cli"] + [str(a) for a in args],
                          cwd=str(cwd), env=mpi_env(), capture_output=True, text=True, timeout=timeout)


def assert_one_line_error(proc, *words):
    assert proc.returncode == 2, describe(proc)
    assert "Traceback" not in proc.stderr, describe(proc)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "error:" in lines[0], describe(proc)
    for w in words:
        assert w in lines[0], (w, describe(proc))


def cloud(n, dim, seed=3, spread=None):
    """A dense random start: centres (n, dim) and diameters (n,) in [0.8, 1.25]."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, dim)) * (spread or 0.5 * n ** (1.0 / dim))
    return x, rng.uniform(0.8, 1.25, size=n)


def load_file(path, *sets):
    return config.load(None, FILE_START + [f'init.file="{path}"'] + list(sets))


def start_of(scene):
    gids = np.arange(scene.n, dtype=np.int64)
    return initial.positions(scene, gids), initial.scene_diameters(scene, gids)


# ---- formats ------------------------------------------------------------------------------------

@pytest.mark.parametrize("dim", [1, 2, 3])
def test_text_and_npy_round_trips(tmp_path, dim):
    x, d = cloud(57, dim)
    rows = np.column_stack([x, d])
    names = ",".join(("x", "y", "z")[:dim] + ("d",))
    np.savetxt(tmp_path / "comma.csv", rows, delimiter=",", header=names, comments="")
    text = "# made by hand\n\n" + "\n".join("   ".join(repr(float(v)) for v in r) + "  # a row"
                                            for r in rows) + "\n\n# the end\n"
    (tmp_path / "space.txt").write_text(text)
    np.save(tmp_path / "rows.npy", rows)
    digests = set()
    for name in ("comma.csv", "space.txt", "rows.npy"):
        scene = load_file(tmp_path / name, f"dim={dim}")
        assert scene.n == 57 and scene.init.file == str(tmp_path / name)
        assert scene.particles.distribution == "file"
        # n from the file sets what depends on it: the automatic iteration bound
        assert scene.stop.max_iter == config.auto_max_iter(57, dim)
        xs, ds = start_of(scene)
        assert np.array_equal(xs, x) and np.array_equal(ds, d), name
        p = scene.particles
        assert (p.d_max, p.d_mean) == (d.max(), pytest.approx(d.mean(), rel=1e-15))
        assert p.mean_radius_power(dim) == pytest.approx(((d / 2) ** dim).mean(), rel=1e-14)
        digests.add(scene.init.sha256)
    assert len(digests) == 1, "the digest is of the numbers, whatever the format"


def test_n_from_the_file_unless_given(tmp_path):
    x, d = cloud(40, 2)
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    assert load_file(tmp_path / "s.npy", "n=40").n == 40
    with pytest.raises(config.SceneError, match=r"key 'n'.*n = 41.*40 rows"):
        load_file(tmp_path / "s.npy", "n=41")
    # a built-in scene's n (paper-2d: 2000) is its default; a user's scene file's n is given
    assert config.load("paper-2d", FILE_START + [f'init.file="{tmp_path / "s.npy"}"']).n == 40
    (tmp_path / "mine.toml").write_text('n = 50\n[init]\nkind = "file"\nfile = "s.npy"\n')
    with pytest.raises(config.SceneError, match="key 'n'"):
        config.load(str(tmp_path / "mine.toml"))
    # a relative path in a scene file is relative to the scene file's folder
    (tmp_path / "mine.toml").write_text('[init]\nkind = "file"\nfile = "s.npy"\n')
    scene = config.load(str(tmp_path / "mine.toml"))
    assert scene.n == 40 and scene.init.file == str(tmp_path / "s.npy")
    # a resolved scene loads back to itself (summary.json, a checkpoint's scene)
    assert config.from_dict(scene.as_dict()) == scene


def test_a_restart_notices_a_changed_file(tmp_path):
    x, d = cloud(30, 2)
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    table = load_file(tmp_path / "s.npy").as_dict()
    assert config.load(None, base=table).init.sha256 == table["init"]["sha256"]
    d[7] *= 1.01
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    with pytest.raises(config.SceneError, match=r"init.sha256.*the file changed"):
        config.load(None, base=table)


def test_conflicting_keys_are_refused_in_one_line(tmp_path):
    x, d = cloud(30, 2)
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    for sets, key in ((['particles.distribution="lognormal"', "particles.spread=0.2"], "particles.distribution"),
                      (["particles.diameter_max=2.0"], "particles.diameter_max"),
                      (["init.iteration=3"], "init.iteration")):
        with pytest.raises(config.SceneError, match=key) as e:
            load_file(tmp_path / "s.npy", *sets)
        assert "\n" not in str(e.value)
    with pytest.raises(config.SceneError, match=r"init.file' applies to init.kind = \"file\""):
        config.load(None, [f'init.file="{tmp_path / "s.npy"}"'])
    with pytest.raises(config.SceneError, match="needs particles.file"):
        config.load(None, ['particles.distribution="file"'])


def test_two_coincident_centres_are_accepted(tmp_path):
    x, d = cloud(20, 2)
    x[5] = x[11]
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    xs, _ = start_of(load_file(tmp_path / "s.npy"))
    assert np.array_equal(xs[5], xs[11])  # the engine separates them (initial.separate)


# ---- runs ---------------------------------------------------------------------------------------

def test_a_run_from_a_file_is_the_same_on_1_2_3_ranks(run_mpipack, tmp_path):
    """A dense start of 240 spheres, two of them at the same centre, read from a CSV: the same
    packing bit for bit on 1, 2 and 3 ranks, and the first snapshot is the file's."""
    x, d = cloud(240, 2)
    x[17] = x[200]
    np.savetxt(tmp_path / "start.csv", np.column_stack([x, d]), delimiter=",", header="x,y,d", comments="")
    runs = {}
    for P in (1, 2, 3):
        proc, summary, dump = run_mpipack(P, None, FILE_START + [f'init.file="{tmp_path / "start.csv"}"'] + SHORT,
                                          dump=True)
        assert proc.returncode == 0 and summary is not None, describe(proc)
        assert summary["n"] == 240 and summary["iterations"] == 200, summary
        runs[P] = (summary, dump)
    s1, d1 = runs[1]
    assert np.array_equal(d1["diam"], d)
    for P in (2, 3):
        assert_bitwise_equal(d1, runs[P][1], f"file start: 1 rank vs {P} ranks")
        assert runs[P][0]["W"] == s1["W"]
    from mpipack.io import list_snapshots, read_snapshot
    snaps = tmp_path / "run1-np1" / "out" / "snapshots.h5"
    first = read_snapshot(snaps, list_snapshots(snaps)[0])[0]
    moved = np.flatnonzero((first["position"] != x).any(axis=1))
    assert set(moved.tolist()) <= {17, 200}, moved  # only the coincident pair was separated
    assert np.array_equal(first["diameter"], d)


def test_a_run_from_a_previous_run(run_mpipack, tmp_path):
    """A run started from another run's last snapshot: by its snapshots.h5 on 1 rank and by its
    folder on 3 ranks, the same packing; its checkpoint gives the positions, not the multipliers."""
    proc, s0, d0 = run_mpipack(1, None, ["n=150", "output.checkpoint_every=200"] + SHORT, dump=True,
                              tag="first")
    assert proc.returncode == 0, describe(proc)
    folder = tmp_path / "first" / "out"
    sets = SHORT[:-2] + ["stop.max_iter=100", "output.progress_every=0"]
    p1, s1, d1 = run_mpipack(1, None, FILE_START + [f'init.file="{folder / "snapshots.h5"}"'] + sets, dump=True)
    p3, s3, d3 = run_mpipack(3, None, FILE_START + [f'init.file="{folder}"'] + sets, dump=True)
    for p, s in ((p1, s1), (p3, s3)):
        assert p.returncode == 0 and s is not None, describe(p)
        assert s["n"] == 150 and s["iterations"] == 100, s  # a new run: its count starts at 0
    assert_bitwise_equal(d1, d3, "from snapshots.h5 on 1 rank vs from the folder on 3 ranks")
    assert np.array_equal(d1["diam"], d0["diam"])
    assert not np.array_equal(d1["x"], d0["x"]), "the second run moved on"
    # the start is the first run's final state: its last snapshot, or its checkpoint
    scene = load_file(folder / "snapshots.h5")
    assert np.array_equal(start_of(scene)[0], d0["x"])
    assert s1["resolved_scene"]["init"]["sha256"] == s3["resolved_scene"]["init"]["sha256"] == scene.init.sha256
    assert s3["resolved_scene"]["init"]["file"] == str(folder)
    from types import SimpleNamespace
    from mpipack.io import read_checkpoint
    block, scalars, _ = read_checkpoint(SimpleNamespace(rank=0, size=1), folder / "checkpoint.h5", parallel=False)
    scene = load_file(folder / "checkpoint.h5")
    xs, ds = start_of(scene)
    assert np.array_equal(xs, block["x"]) and np.array_equal(ds, block["diam"])
    assert np.array_equal(xs, d0["x"])
    # init.iteration picks an earlier snapshot
    scene = load_file(folder / "snapshots.h5", "init.iteration=0")
    assert not np.array_equal(start_of(scene)[0], d0["x"])


def test_diameters_from_a_file_of_n_rows_and_of_fewer(run_mpipack, tmp_path):
    rng = np.random.default_rng(5)
    full, few = rng.uniform(0.7, 1.4, size=160), rng.uniform(0.7, 1.4, size=23)
    np.save(tmp_path / "full.npy", full)
    (tmp_path / "few.csv").write_text("d\n" + "\n".join(repr(float(v)) for v in few) + "\n")
    scene = config.load(None, ["n=160", 'particles.distribution="file"', f'particles.file="{tmp_path / "full.npy"}"'])
    assert np.array_equal(initial.scene_diameters(scene, np.arange(160)), full)
    scene = config.load(None, ["n=160", 'particles.distribution="file"', f'particles.file="{tmp_path / "few.csv"}"'])
    assert scene.particles.d_max == few.max() and scene.particles.d_mean == pytest.approx(few.mean(), rel=1e-15)
    d = initial.scene_diameters(scene, np.arange(160))
    assert set(d.tolist()) <= set(few.tolist()) and len(set(d.tolist())) > 15
    # a function of (seed, gid): any block of gids gets the same rows
    blocks = np.concatenate([initial.scene_diameters(scene, np.arange(a, b)) for a, b in ((0, 7), (7, 99), (99, 160))])
    assert np.array_equal(blocks, d)
    other = config.load(None, ["n=160", "seed=2", 'particles.distribution="file"', f'particles.file="{tmp_path / "few.csv"}"'])
    assert not np.array_equal(initial.scene_diameters(other, np.arange(160)), d)
    sets = ["n=160", 'particles.distribution="file"', f'particles.file="{tmp_path / "few.csv"}"'] + SHORT
    runs = [run_mpipack(P, None, sets, dump=True) for P in (1, 3)]
    for proc, summary, _ in runs:
        assert proc.returncode == 0 and summary is not None, describe(proc)
    assert np.array_equal(runs[0][2]["diam"], d)
    assert_bitwise_equal(runs[0][2], runs[1][2], "diameters file: 1 rank vs 3 ranks")


def test_check_counts_the_pairs_of_a_file_start(tmp_path):
    x, d = cloud(90, 2)
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    proc = cli(["check"] + sum((["--set", s] for s in FILE_START + [f'init.file="{tmp_path / "s.npy"}"']), []), tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert "N=90" in proc.stdout and str(tmp_path / "s.npy") in proc.stdout
    r = np.sqrt(((x[:, None] - x[None]) ** 2).sum(axis=2))
    pairs = int(np.count_nonzero(np.triu(r <= d.mean(), 1)))
    assert f"overlapping pairs at the start ~ {pairs:.4g} " in proc.stdout, (pairs, proc.stdout)


# ---- bad files ----------------------------------------------------------------------------------

def _header_only_npy(path, rows, cols):
    """A .npy header that announces (rows, cols) float64, without the data: the reader must
    refuse it from its header."""
    from numpy.lib import format as npy
    with open(path, "wb") as fh:
        npy.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (rows, cols)})


BAD = {
    # name: (file name, content (bytes, or a function of the path), words of the message)
    "missing": ("nope.csv", None, ["no such file"]),
    "binary": ("junk.csv", b"\xff\xfe\x00\x01\x02", ["not a text file"]),
    "truncated npy": ("cut.npy", lambda p: p.write_bytes(_npy_bytes(np.ones((10, 3)))[:90]), ["not a readable .npy"]),
    "truncated npy data": ("cut2.npy", lambda p: p.write_bytes(_npy_bytes(np.ones((10, 3)))[:-8]), ["not a readable .npy"]),
    "npy of strings": ("words.npy", lambda p: np.save(p, np.array([["a", "b", "c"]])), ["not numbers"]),
    "foreign hdf5": ("other.h5", "h5", ["not an mpipack"]),
    "empty": ("empty.csv", b"", ["empty file"]),
    "header only": ("head.csv", b"x,y,d\n# nothing\n", ["header only"]),
    "nan": ("nan.csv", b"x,y,d\n0,0,1\n1,nan,1\n", ["line 3", "not a finite number"]),
    "inf diameter": ("inf.txt", b"0 0 1\n1 1 inf\n", ["line 2", "not a finite number"]),
    "negative diameter": ("neg.csv", b"0,0,1\n# c\n1,1,-0.5\n", ["line 3", "-0.5"]),
    "zero diameter": ("zero.npy", lambda p: np.save(p, np.array([[0, 0, 1.0], [1, 1, 0.0]])), ["row 1", "0.0"]),
    "short row": ("short.csv", b"0,0,1\n1,1,1\n\n2,2\n3,3,1\n", ["line 4", "2 numbers, expected 3"]),
    "not a number": ("word.csv", b"0,0,1\n1,one,1\n", ["line 2", "'one' is not a number"]),
    "dim mismatch": ("three.csv", b"0,0,0,1\n1,1,1,1\n", ["4 columns", "2D has 3"]),
    "too many rows": ("huge.npy", lambda p: _header_only_npy(p, 10 ** 8 + 1, 3), ["100000001 rows"]),
}


def _npy_bytes(a):
    import io
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def _make(tmp_path, name):
    fname, content, words = BAD[name]
    path = tmp_path / fname
    if content == "h5":
        import h5py
        with h5py.File(path, "w") as f:
            f["x"] = np.ones(3)
    elif callable(content):
        content(path)
    elif content is not None:
        path.write_bytes(content)
    return path, words


@pytest.mark.parametrize("name", list(BAD))
def test_a_bad_start_file_is_refused_in_one_line(tmp_path, name):
    path, words = _make(tmp_path, name)
    proc = cli(["run", "--quiet", "--out", tmp_path / "o", "--set", FILE_START[0], "--set", f'init.file="{path}"'],
               tmp_path)
    assert_one_line_error(proc, "init.file", str(path), *words)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("name", ["nan", "dim mismatch", "missing"])
def test_check_refuses_a_bad_start_file(tmp_path, name):
    path, words = _make(tmp_path, name)
    proc = cli(["check", "--set", FILE_START[0], "--set", f'init.file="{path}"'], tmp_path)
    assert_one_line_error(proc, "init.file", *words)


@pytest.mark.parametrize("content,words", [
    (b"1.0\n-2.0\n", ["line 2", "-2.0"]),
    (b"1.0 1.0\n", ["2 columns", "diameters file has 1"]),
    (b"", ["empty file"]),
])
def test_a_bad_diameters_file_is_refused_in_one_line(tmp_path, content, words):
    (tmp_path / "d.txt").write_bytes(content)
    proc = cli(["run", "--quiet", "--out", tmp_path / "o", "--set", 'particles.distribution="file"',
                "--set", f'particles.file="{tmp_path / "d.txt"}"'], tmp_path)
    assert_one_line_error(proc, "particles.file", *words)


def test_a_file_start_restarts_and_a_changed_file_is_refused(run_mpipack, tmp_path):
    """--restart of a run started from a file re-reads the file: the same numbers continue, changed
    numbers are refused (exit 2, one line) before anything is written."""
    x, d = cloud(60, 2)
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    sets = FILE_START + [f'init.file="{tmp_path / "s.npy"}"', "output.checkpoint_every=50"] + SHORT[:-2] \
        + ["stop.max_iter=100", "output.progress_every=0"]
    proc, summary, _ = run_mpipack(1, None, sets, tag="first")
    assert proc.returncode == 0 and summary["n"] == 60, describe(proc)
    checkpoint = tmp_path / "first" / "out" / "checkpoint.h5"
    proc = cli(["run", "--quiet", "--restart", checkpoint, "--set", "stop.max_iter=150", "--out", tmp_path / "again"],
               tmp_path)
    assert proc.returncode == 0, describe(proc)
    again = json.loads((tmp_path / "again" / "summary.json").read_text())
    assert again["iterations"] == 150 and again["resolved_scene"]["init"]["sha256"] == summary["resolved_scene"]["init"]["sha256"]
    d[3] *= 1.5
    np.save(tmp_path / "s.npy", np.column_stack([x, d]))
    proc = cli(["run", "--quiet", "--restart", checkpoint, "--set", "stop.max_iter=150", "--out", tmp_path / "third"],
               tmp_path)
    assert_one_line_error(proc, "init.sha256", "the file changed")
    assert not (tmp_path / "third").exists()
