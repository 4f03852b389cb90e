"""Containers (``container.kind``), the point potential and gravity (``potential.kind``): the
walls' geometry, one sphere pulled against a wall and one resting on a floor (their exact fixed
points and wall forces), a single layer on a floor, the same packing on 1, 2 and 3 ranks, a
restart onto another rank count, one-line errors for bad keys and for a container too small for
its spheres, and old scenes (without the new sections) still restart."""

import math

import numpy as np
import pytest

from conftest import assert_bitwise_equal, describe, mpipack_run
from mpipack import config
from mpipack.engine import initial
from mpipack.kernels import walls

BOX2 = ["container.kind=box", "container.lo=[-6.0, -6.0]", "container.hi=[6.0, 6.0]"]
CYL3 = ["dim=3", "container.kind=cylinder", "container.centre=[0.0, 0.0, 0.0]", "container.radius=2.6",
        "container.height=5.0"]


def test_wall_geometry():
    """Signed distances (positive inside) and inward normals of each kind of wall."""
    box = walls.walls_of(config.load(None, ["n=10"] + BOX2).container, 2)
    assert box.shape == (4, walls.WALL_WIDTH)
    got = [walls.gap(2, box, w, 1.0, -2.0, 0.0) for w in range(4)]
    assert [g[0] for g in got] == [7.0, 5.0, 4.0, 8.0]  # x - lo, hi - x, y - lo, hi - y
    assert [g[1:3] for g in got] == [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)]
    cyl = walls.walls_of(config.load(None, ["n=10"] + CYL3).container, 3)
    s, n0, n1, n2, curv = walls.gap(3, cyl, 0, 3.0, 4.0, 1.0)  # the side, 5 from the axis
    assert (s, n0, n1, n2) == pytest.approx((2.6 - 5.0, -0.6, -0.8, 0.0)) and curv == pytest.approx(0.2)
    assert walls.gap(3, cyl, 1, 0.0, 0.0, 1.5)[:4] == (1.5, 0.0, 0.0, 1.0)  # the floor
    assert walls.gap(3, cyl, 2, 0.0, 0.0, 1.5)[:4] == (3.5, 0.0, 0.0, -1.0)  # the lid
    ball = walls.walls_of(config.load(None, ["n=10", "container.kind=sphere", "container.centre=[1.0, 1.0]",
                                             "container.radius=10.0"]).container, 2)
    s, n0, n1, _, _ = walls.gap(2, ball, 0, 4.0, 5.0, 0.0)
    assert (s, n0, n1) == pytest.approx((5.0, -0.6, -0.8))
    assert walls.walls_of(config.load(None, ["n=10"]).container, 2).shape == (0, walls.WALL_WIDTH)


def test_the_start_is_inside():
    scene = config.load(None, ["n=100"] + CYL3)
    gids = np.arange(scene.n)
    d = initial.scene_diameters(scene, gids)
    x = initial.contain(scene, initial.positions(scene, gids), d)
    assert walls.max_outside(x, scene.n, d, walls.walls_of(scene.container, 3)) <= 1e-12


@pytest.mark.mpi
@pytest.mark.parametrize("form", ["S", "NS"])
def test_one_sphere_pulled_against_a_wall(run_mpipack, form):
    """W = |X - P|^2 / 2 with P = (10, 0) beyond the wall x = 5: the minimiser touches the wall,
    X = (5 - d/2, 0), and the wall's force balances the pull: |X - P| = 5.5 in either form."""
    proc, summary, dump = run_mpipack(1, sets=["n=1", f"method.form={form}", "container.kind=box",
                                               "container.lo=[-5.0, -5.0]", "container.hi=[5.0, 5.0]",
                                               "potential.kind=point", "potential.point=[10.0, 0.0]"],
                                      dump=True)
    assert proc.returncode == 0 and summary["converged"] is True, describe(proc)
    x = dump["x"][0]
    assert abs(x[0] - 4.5) < 1e-4 and abs(x[1]) < 1e-3
    assert summary["W"] == pytest.approx(0.5 * 5.5 ** 2, rel=1e-3)
    import mpipack
    out = proc.args[proc.args.index("--out") + 1]
    snap = mpipack.read_snapshot(out)  # the last snapshot: the final state
    assert snap.fields["wall_force"][0] == pytest.approx(5.5, rel=1e-3)
    assert snap.fields["contacts"][0] == 1


@pytest.mark.mpi
@pytest.mark.parametrize("form", ["S", "NS"])
def test_one_sphere_on_a_floor(run_mpipack, form):
    """W = g m h (m = 1: the mean diameter): the sphere rests on the floor, h = d/2, and the
    floor carries its weight, m g = 2 (g = 2)."""
    proc, summary, dump = run_mpipack(1, sets=["n=1", f"method.form={form}", "container.kind=box",
                                               "container.lo=[-5.0, 0.0]", "container.hi=[5.0, 10.0]",
                                               "potential.kind=gravity", "potential.g=2.0"], dump=True)
    assert proc.returncode == 0 and summary["converged"] is True, describe(proc)
    assert abs(dump["x"][0, 1] - 0.5) < 1e-3 and -4.5 <= dump["x"][0, 0] <= 4.5
    assert summary["W"] == pytest.approx(2.0 * 0.5, rel=2e-3)
    import mpipack
    snap = mpipack.read_snapshot(proc.args[proc.args.index("--out") + 1])
    assert snap.fields["wall_force"][0] == pytest.approx(2.0, rel=1e-3)


@pytest.mark.mpi
def test_a_single_layer_on_a_floor(run_mpipack):
    """Ten discs of diameter 1 in a box exactly ten wide settle into one row on its floor: the
    known packing, every centre at height 1/2 and 1 apart (to the overlap tolerance)."""
    proc, summary, dump = run_mpipack(1, sets=["n=10", "dim=2", "particles.distribution=mono",
                                               "container.kind=box", "container.lo=[0.0, 0.0]",
                                               "container.hi=[10.0, 30.0]", "potential.kind=gravity"],
                                      dump=True)
    assert proc.returncode == 0 and summary["converged"] is True, describe(proc)
    x = dump["x"][np.argsort(dump["x"][:, 0])]
    assert np.abs(x[:, 1] - 0.5).max() < 2e-3, x
    assert np.abs(x[:, 0] - (np.arange(10) + 0.5)).max() < 1e-2, x
    assert summary["W"] == pytest.approx(10 * 0.5, rel=2e-3)


@pytest.mark.mpi
@pytest.mark.parametrize("case", ["box-2d", "cylinder-3d", "gravity-box-2d", "gravity-cylinder-3d"])
def test_the_same_packing_on_1_2_3_ranks(run_mpipack, case):
    sets = {"box-2d": ["n=150"] + BOX2, "cylinder-3d": ["n=100"] + CYL3,
            "gravity-box-2d": ["n=150", "potential.kind=gravity", "container.kind=box",
                               "container.lo=[-5.0, 0.0]", "container.hi=[5.0, 40.0]"],
            "gravity-cylinder-3d": ["n=150", "dim=3", "potential.kind=gravity", "container.kind=cylinder",
                                    "container.centre=[0.0, 0.0, 0.0]", "container.radius=2.5"]}[case]
    ref = None
    for ranks in (1, 2, 3):
        proc, summary, dump = run_mpipack(ranks, sets=sets, dump=True, tag=f"np{ranks}")
        assert proc.returncode == 0, describe(proc)
        assert summary["converged"] is True and summary["max_overlap"] <= 1e-3
        if ref is None:
            ref = dump
            scene = config.load(None, sets)
            w = walls.walls_of(scene.container, scene.dim)
            # no sphere beyond a wall by more than the overlap tolerance
            assert walls.max_outside(dump["x"], scene.n, dump["diam"], w) <= 1e-3
        else:
            assert_bitwise_equal(ref, dump, f"{case} on {ranks} ranks")


@pytest.mark.mpi
def test_restart_onto_another_rank_count(tmp_path):
    """Under gravity in a box: the walls' multipliers and W's figures continue bit for bit."""
    sets = ["n=150", "stop.rule=eps", "stop.eps=0", "potential.kind=gravity", "container.kind=box",
            "container.lo=[-5.0, 0.0]", "container.hi=[5.0, 40.0]"]
    for d in ("ref", "run"):
        (tmp_path / d).mkdir()
    p_ref, s_ref, d_ref = mpipack_run(1, tmp_path / "ref", None, sets + ["stop.max_iter=1500"], dump=True)
    assert p_ref.returncode == 0, describe(p_ref)
    p1, s1, _ = mpipack_run(3, tmp_path / "run", None, sets + ["stop.max_iter=700", "output.checkpoint_every=700"])
    assert p1.returncode == 0 and s1["checkpoint"]["iteration"] == 700, describe(p1)
    p2, s2, d2 = mpipack_run(2, tmp_path / "run", None, ["stop.max_iter=1500"], dump=True,
                             extra=["--restart", tmp_path / "run" / "out"])
    assert p2.returncode == 0 and s2["iterations"] == 1500, describe(p2)
    assert_bitwise_equal(d_ref, d2, "gravity box: 3 ranks to 700, then 2 ranks to 1500")
    assert s2["W"] == s_ref["W"]


@pytest.mark.parametrize("sets,words", [
    (["container.kind=jar"], "must be one of"),
    (["container.kind=box"], "needs container.lo"),
    (["container.kind=box", "container.lo=[0, 0]", "container.hi=[50]", ], "list of 2 finite numbers"),
    (["container.kind=box", "container.lo=[0, 0]", "container.hi=[50, 0.5]"], "narrower than"),
    (["container.kind=sphere", "container.centre=[0, 0]", "container.radius=10", "container.lo=[0, 0]"],
     "does not apply"),
    (["container.kind=cylinder", "container.centre=[0, 0]", "container.radius=30"], "3D container"),
    (["container.kind=sphere", "container.centre=[0, 0]", "container.radius=20"], "too small"),
    (["potential.kind=point"], "needs potential.point"),
    (["potential.kind=magnetic"], "must be one of"),
    (["potential.kind=gravity"], "needs a container"),
    (["potential.kind=gravity", "potential.g=-1"] + BOX2 + ["n=100"], "must be positive"),
    (["potential.g=2"], "does not apply"),
    (["potential.point=[1, 2]"], "does not apply"),
])
def test_bad_container_and_potential_keys(sets, words):
    with pytest.raises(config.SceneError, match=words):
        config.load(None, sets)


@pytest.mark.parametrize("method", ["nap", "nav"])
@pytest.mark.parametrize("sets", [
    ["container.kind=sphere", "container.centre=[0, 0]", "container.radius=40"],
    ["potential.kind=point", "potential.point=[1, 2]"],
    ["potential.kind=gravity"] + BOX2 + ["n=100"],
])
def test_nested_methods_take_containers_and_potentials(method, sets):
    """NAP and NAV, like DAHA, take the walls and the potentials (their runs:
    tests/test_container_nested.py)."""
    from mpipack.methods import for_scene
    scene = config.load(None, sets + [f"method.name={method}", "method.alpha=0.1", "method.beta=0.1"])
    m = for_scene(scene)
    assert m.name == method and m.gravity == (scene.potential.kind == "gravity")


@pytest.mark.mpi
@pytest.mark.parametrize("command", ["run", "check"])
def test_a_container_too_small_is_refused_in_one_line(tmp_path, command):
    """2000 spheres of diameter 1 in a disc of radius 20: 1571 of area, more than the 1140 a
    disc of that size holds at the hexagonal packing's 0.9069."""
    import subprocess
    import sys
    from conftest import mpi_env
    args = [sys.executable, "-m", "mpipack.cli", command, "--set", "container.kind=sphere",
            "--set", "container.centre=[0.0, 0.0]", "--set", "container.radius=20"]
    if command == "run":
        args += ["--out", str(tmp_path / "out")]
    proc = subprocess.run(args, cwd=tmp_path, env=mpi_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, describe(proc)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "too small" in lines[0], proc.stderr
    assert not (tmp_path / "out").exists()


def test_old_scenes_without_the_new_sections_restart():
    new = config.load(None, []).as_dict()
    old = {k: v for k, v in new.items() if k not in ("container", "potential")}
    assert config.physics_changes(old, new) == []
    boxed = config.load(None, ["container.kind=box", "container.lo=[-30.0, -30.0]",
                               "container.hi=[30.0, 30.0]"]).as_dict()
    assert "container.kind ('none' -> 'box')" in config.physics_changes(old, boxed)
    assert math.isinf(config.load(None, []).container.volume(2))
