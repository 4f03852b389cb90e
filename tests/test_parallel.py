"""``mpirun -n P mpipack run``: rank-count independence, empty ranks, error exits, the main job.

Every run goes through the real command line (python -m mpipack.cli) under mpirun, with its
output captured and shown on failure.
"""

import subprocess
import sys
import time

import numpy as np
import pytest

from support import brute_force_figures

from conftest import MPI_SCRIPTS, TIMEOUT, assert_bitwise_equal, describe, mpi_env, mpirun



def assert_ok(proc, summary):
    assert proc.returncode == 0, describe(proc)
    assert summary is not None, "no summary.json" + describe(proc)
    assert "Traceback" not in proc.stderr, describe(proc)


def force_pairs(summary, d):
    """Pairs that carry a force multiplier of the fire-al certificate, from a dump (brute force):
    mu = max(0, lambda + pen max(lambda, floor) phi / d^p) > 0 and a gap within the overlap
    tolerance."""
    from mpipack.methods import fire_al_schedule as schedule
    x, diam, n = d["x"], d["diam"], d["x"].shape[0]
    form = summary["form"]
    law = schedule.packing_law(n, summary["dim"], 0.5 * (diam.min() + diam.max()), form)
    floor, pen = schedule.FLOOR * law["lam_bar"], summary["schedule"]["penalty_factor"]
    tol = summary["certificate"]["overlap"]["tol"]
    lam = np.zeros((n, n))
    lam[d["pairs_gid"][:, 0], d["pairs_gid"][:, 1]] = d["pairs_lambda"]
    r = np.sqrt(((x[:, None, :] - x[None, :, :]) ** 2).sum(axis=2))
    dij = 0.5 * (diam[:, None] + diam[None, :])
    phi_unit = (dij * dij - r * r) / (dij * dij) if form == "S" else (dij - r) / dij
    mu = np.maximum(0.0, lam + pen * np.maximum(lam, floor) * phi_unit)
    mu[r > dij * (1.0 + tol)] = 0.0
    return int(np.count_nonzero(np.triu(mu, 1)))


def check_dump_consistency(summary, d):
    n = summary["n"]
    assert np.array_equal(d["gid"], np.arange(n))
    assert d["x"].shape == (n, summary["dim"])
    pg = d["pairs_gid"]
    assert pg.ndim == 2 and pg.shape[1] == 2 and np.all(pg[:, 0] < pg[:, 1])
    assert np.all(d["pairs_lambda"] > 0)
    assert len({tuple(p) for p in pg.tolist()}) == pg.shape[0], "duplicate pairs in the dump"
    if summary["parameters"].get("schedule") == "fire-al" and summary["schedule"]["phase"] == "fire":
        assert summary["active_pairs"] == force_pairs(summary, d)
    else:
        assert summary["active_pairs"] == pg.shape[0]
    w, ov = brute_force_figures(d)
    assert summary["W"] == pytest.approx(w, rel=1e-10)
    assert summary["max_overlap"] == pytest.approx(ov, rel=1e-9, abs=1e-15)


# ---------------------------------------------------------------------------------------------
# bitwise equality across rank counts
# ---------------------------------------------------------------------------------------------

SCENES = {
    # the Gaussian start expands: particles cross rank boundaries and rows are rebuilt often
    "2d-paper": ("paper-2d", ["n=400", "stop.eps=0", "stop.max_iter=300"]),
    "3d-paper": ("paper-3d", ["n=400", "stop.eps=0", "stop.max_iter=300"]),
    # the fire-al schedule: explosion, then FIRE with ALM steps and momentum restarts, every
    # decision from reduced figures
    "2d-fire-al": (None, ["n=400", "stop.rule=eps", "stop.eps=0", "stop.max_iter=1000"]),
    "3d-fire-al-ns": (None, ["n=400", "dim=3", "method.form=NS", "stop.rule=eps", "stop.eps=0",
                             "stop.max_iter=300"]),
    # a disordered packing: the penalty factor grows (x8 from 16 in 3D, to 1024 within these 3000
    # iterations) at multiplier steps, the continuous dual stops; at the cap the inner solves
    # are L-BFGS's (iteration ~1240 on: Gram matrix from exact sums, memory migrating)
    "3d-fire-al-penalty": (None, ["n=200", "dim=3", "stop.rule=eps", "stop.eps=0", "stop.max_iter=3000"]),
}


@pytest.mark.parametrize("name", list(SCENES))
def test_same_bits_on_1_2_3_ranks(run_mpipack, name):
    scene, sets = SCENES[name]
    runs = {}
    for P in (1, 2, 3):
        proc, summary, dump = run_mpipack(P, scene, sets, dump=True)
        assert_ok(proc, summary)
        assert dump is not None, describe(proc)
        max_iter = int(next(x for x in sets if x.startswith("stop.max_iter="))[14:])
        assert summary["ranks"] == P and summary["iterations"] == max_iter
        assert summary["rebuilds"] > 1, summary
        runs[P] = (summary, dump)
    s1, d1 = runs[1]
    check_dump_consistency(s1, d1)
    assert d1["pairs_gid"].shape[0] > 50, "test set-up: want many contacts at the end"
    if name == "3d-fire-al-penalty":
        from mpipack.methods import fire_al_schedule as schedule
        assert s1["schedule"]["penalty_factor"] > schedule.C_B[3], s1["schedule"]
        assert s1["schedule"]["lbfgs_from"] < 2000, s1["schedule"]
    for P in (2, 3):
        s, d = runs[P]
        assert_bitwise_equal(d1, d, f"{name}: 1 rank vs {P} ranks")
        for key in ("W", "max_overlap", "relative_change", "density", "active_pairs", "rebuilds",
                    "max_net_force", "net_force_share"):
            assert s[key] == s1[key], (key, P, s[key], s1[key])
        assert s["rebalances"] >= 1, s
        if "schedule" in s:  # the dense start was spread into a ball: every sphere migrated
            assert s["schedule"]["spread"] is True, s
            assert s["schedule"] == s1["schedule"], (P, s["schedule"], s1["schedule"])
        else:  # particles crossed rank boundaries: pair partners had to be fetched from afar
            assert s["far_ghosts"] > 0, s


def test_shortened_lbfgs_steps_same_bits_on_1_2_3_ranks(run_mpipack):
    """Five spheres in 3D (seed 7): the L-BFGS phase's shortened steps fail their descent test
    again and again (the slope g_old.s is an exact sum of the reduction), halving the gradient
    scale; the decisions and the iterates are the same on 1, 2 and 3 ranks (some of them
    empty)."""
    sets = ["n=5", "dim=3", "seed=7", "stop.rule=eps", "stop.eps=0", "stop.max_iter=600"]
    runs = {}
    for P in (1, 2, 3):
        proc, summary, dump = run_mpipack(P, None, sets, dump=True)
        assert_ok(proc, summary)
        runs[P] = (summary, dump)
    s1, d1 = runs[1]
    assert s1["schedule"]["lbfgs_rejected"] > 10 and s1["schedule"]["lbfgs_shortened"] > 10, s1["schedule"]
    for P in (2, 3):
        s, d = runs[P]
        assert_bitwise_equal(d1, d, f"1 rank vs {P} ranks")
        assert s["schedule"] == s1["schedule"] and s["W"] == s1["W"], (P, s["schedule"])


def test_empty_rank_two_spheres(run_mpipack):
    """n = 2 on 3 ranks: one rank owns nothing, all the time."""
    p1, s1, d1 = run_mpipack(1, "two-spheres", [], dump=True)
    p3, s3, d3 = run_mpipack(3, "two-spheres", [], dump=True)
    assert_ok(p1, s1)
    assert_ok(p3, s3)
    assert s1["converged"] and s3["converged"]
    assert s3["iterations"] == s1["iterations"]
    assert_bitwise_equal(d1, d3, "two-spheres: 1 rank vs 3 ranks")
    assert abs(abs(d3["x"][1, 0] - d3["x"][0, 0]) - 1.0) < 1e-8
    assert d3["pairs_gid"].tolist() == [[0, 1]]
    assert abs(d3["pairs_lambda"][0] - 0.5) < 1e-8


def test_five_spheres_on_3_ranks(run_mpipack):
    """n = 5 in 2D, polydisperse, DAHA-NS: converges to a cluster with contacts across ranks."""
    sets = ["dim=2", "n=5", "particles.diameter_max=1.3", "stop.eps=1e-10"]
    p1, s1, d1 = run_mpipack(1, "two-spheres", sets, dump=True)
    p3, s3, d3 = run_mpipack(3, "two-spheres", sets, dump=True)
    assert_ok(p1, s1)
    assert_ok(p3, s3)
    assert s1["converged"] and s3["converged"] and s1["iterations"] == s3["iterations"]
    assert_bitwise_equal(d1, d3, "5 spheres: 1 rank vs 3 ranks")
    check_dump_consistency(s3, d3)
    assert d3["pairs_gid"].shape[0] >= 4, "five spheres in contact need at least 4 contacts"
    assert s3["max_overlap"] < 1e-6
    assert len(np.unique(d3["diam"])) == 5 and d3["diam"].min() >= 1.0 and d3["diam"].max() <= 1.3


# ---------------------------------------------------------------------------------------------
# errors: every rank exits with the code, one line naming the key, no traceback
# ---------------------------------------------------------------------------------------------

BAD_INPUT = [
    (["--set", "bogus=1"], "bogus"),
    (["--set", "method.alhpa=0.3"], "method.alhpa"),
    (["--set", "n=0"], "'n'"),
    (["--set", "n=abc"], "'n'"),
    (["--set", "dim=4"], "'dim'"),
    (["--set", "method.alpha=-1"], "method.alpha"),
    (["--set", "method.c=0"], "method.c"),
    (["--set", "particles.diameter=0"], "particles.diameter"),
    (["--set", "method.form=X"], "method.form"),
]


def error_line(proc):
    lines = [l for l in proc.stderr.splitlines() if l.startswith("mpipack: error:")]
    assert len(lines) == 1, "want exactly one 'mpipack: error:' line" + describe(proc)
    return lines[0]


@pytest.mark.parametrize("args,key", BAD_INPUT, ids=[a[1] for a, _ in BAD_INPUT])
def test_bad_input_exits_2(run_mpipack, args, key):
    t0 = time.monotonic()
    proc, summary, _ = run_mpipack(2, None, extra=args, timeout=120)
    elapsed = time.monotonic() - t0
    assert proc.returncode == 2, describe(proc)
    assert key in error_line(proc), describe(proc)
    assert "Traceback" not in proc.stderr + proc.stdout, describe(proc)
    assert summary is None
    assert elapsed < 60, f"bad input took {elapsed:.1f} s to be reported" + describe(proc)


def test_bad_scene_file_exits_2(run_mpipack, tmp_path):
    f = tmp_path / "typo.toml"
    f.write_text('dim = 2\nn = 10\n[method]\nname = "daha"\nbeta_ = 3.0\n')
    proc, summary, _ = run_mpipack(2, str(f), timeout=120)
    assert proc.returncode == 2, describe(proc)
    assert "method.beta_" in error_line(proc)
    assert "Traceback" not in proc.stderr
    proc, _, _ = run_mpipack(2, "no-such-scene", timeout=120)
    assert proc.returncode == 2, describe(proc)
    assert "no-such-scene" in error_line(proc)


def test_out_of_range_seed_is_bad_input(run_mpipack):
    proc, _, _ = run_mpipack(2, "two-spheres", extra=["--seed", str(2 ** 64)], timeout=120)
    assert proc.returncode == 2, describe(proc)
    assert "seed" in error_line(proc)
    assert "Traceback" not in proc.stderr


def test_divergence_exits_3(run_mpipack):
    proc, summary, _ = run_mpipack(2, None, ["n=400", "method.alpha=30"], timeout=120)
    assert proc.returncode == 3, describe(proc)
    line = error_line(proc)
    assert "diverg" in line or "NaN" in line, describe(proc)
    assert "iteration" in line
    assert "Traceback" not in proc.stderr, describe(proc)
    # summary.json on every exit, with the error
    assert summary["exit_code"] == 3 and summary["error"] == line.split("error: ", 1)[1], summary


def test_not_converged_exits_4(run_mpipack):
    proc, summary, _ = run_mpipack(2, None, ["n=200", "stop.max_iter=50"], timeout=120, quiet=False)
    assert proc.returncode == 4, describe(proc)
    assert summary is not None and summary["converged"] is False and summary["iterations"] == 50
    assert summary["relative_change"] >= summary["eps"]
    # the KKT criterion failed: the summary and the printed result say where the residual sits
    assert not summary["certificate"]["kkt"]["ok"]
    assert summary["max_net_force"] > 0 and 0 < summary["net_force_share"] <= 1, summary
    assert "of the run's squared KKT residual (an even spread: 1/N = 5.0e-03)" in proc.stdout, describe(proc)


# ---------------------------------------------------------------------------------------------
def test_certified_by_fitted_multipliers_on_1_2_3_ranks(run_mpipack):
    """A run certified by the multiplier fit (2D N = 2000 seed 5, certified at 2650: the run's own
    multipliers leave a KKT residual of 0.032 at the stop, the fitted ones 0.0072): the same
    stop, certificate and packing, bit for bit, on 1, 2 and 3 ranks."""
    runs = {}
    for P in (1, 2, 3):
        proc, s, d = run_mpipack(P, None, ["seed=5"], dump=True)
        assert_ok(proc, s)
        runs[P] = (s, d)
    s1, d1 = runs[1]
    kkt = s1["certificate"]["kkt"]
    assert s1["converged"] and s1["stop_reason"] == "certified", s1["certificate"]
    assert kkt["multipliers"] == "fitted" and kkt["value"] <= kkt["tol"] < kkt["run_value"], kkt
    assert s1["kkt_residual"] == kkt["value"] and s1["kkt_residual_run"] == kkt["run_value"], s1
    for P in (2, 3):
        s, d = runs[P]
        assert s["iterations"] == s1["iterations"] and s["certificate"] == s1["certificate"], (P, s["certificate"])
        assert_bitwise_equal(d1, d, f"fitted certificate: 1 rank vs {P} ranks")


# the main job: the paper's section 4.3 case on 2 ranks
# ---------------------------------------------------------------------------------------------


def test_default_scene_converges_on_2_ranks(run_mpipack):
    """The main job: certified (every criterion met), the same packing bit for bit on 1 rank."""
    proc, s, d = run_mpipack(2, None, [], dump=True, quiet=False)
    assert_ok(proc, s)
    # progress from rank 0 only: one header, one verdict
    assert proc.stdout.count("mpipack: scene default: DAHA-S dim=2 N=2000 on 2 rank(s); schedule fire-al") == 1, describe(proc)
    assert proc.stdout.count(f"mpipack: converged (certified) after {s['iterations']} iterations") == 1, describe(proc)
    assert s["scene"] == "default" and s["method"] == "daha" and s["form"] == "S"
    assert s["dim"] == 2 and s["n"] == 2000 and s["ranks"] == 2
    assert s["stop_reason"] == "certified" and s["converged"] is True, s
    assert all(c["ok"] for c in s["certificate"].values()), s["certificate"]
    assert s["max_overlap"] <= 1e-3 and s["kkt_residual"] <= 1e-2, s
    assert s["schedule"]["phase"] == "fire" and s["schedule"]["dual_steps"] >= 1, s
    # measured 2950-12000 iterations on seeds 0-19 (docs/research/convergence.md)
    assert 0 < s["iterations"] < 15000, s
    # a nearly hexagonal packing: below the optimum pi / (2 sqrt 3) = 0.907, well above the
    # paper's 0.87
    assert 0.87 < s["density"] < 0.907, s
    assert s["active_pairs"] > 2000  # a packed cloud: well over one contact per sphere
    assert s["rebuilds"] > 1 and s["schedule"]["spread"] is True, s
    check_dump_consistency(s, d)
    # the same certified packing, bit for bit, on one rank
    p1, s1, d1 = run_mpipack(1, None, [], dump=True)
    assert_ok(p1, s1)
    assert s1["iterations"] == s["iterations"] and s1["W"] == s["W"]
    assert_bitwise_equal(d1, d, "default scene: 1 rank vs 2 ranks")


def test_paper_scene_says_what_4_3_does_not_guarantee(run_mpipack):
    """The paper's section 4.3 case: (4.3) fires, and the certificate says it is not a packing
    in force balance."""
    proc, s, _ = run_mpipack(2, "paper-2d", [], quiet=False)
    assert_ok(proc, s)
    assert proc.stdout.count(f"mpipack: stopped by (4.3), NOT certified after {s['iterations']} iterations") == 1, describe(proc)
    assert s["stop_reason"] == "eps" and s["converged"] is False, s
    assert s["certificate"]["overlap"]["ok"] and not s["certificate"]["kkt"]["ok"], s
    assert 0 < s["iterations"] < 13000, s  # paper: fewer than 13000 iterations
    # paper, Fig. 8: density about 0.87, below the hexagonal optimum pi / (2 sqrt 3) = 0.907
    assert 0.80 < s["density"] < 0.907, s


def test_scenes_command():
    proc = subprocess.run([sys.executable, "-m", "mpipack.cli", "scenes"], env=mpi_env(),
                          capture_output=True, text=True, timeout=TIMEOUT)
    assert proc.returncode == 0, describe(proc)
    assert {"default", "paper-3d", "two-spheres"} <= set(proc.stdout.split()), describe(proc)


def test_dump_into_missing_folder(run_mpipack, tmp_path):
    target = tmp_path / "no" / "such" / "dir" / "final.npz"
    proc, _, _ = run_mpipack(2, "two-spheres", extra=["--dump", str(target)], timeout=120)
    assert "Traceback" not in proc.stderr, describe(proc)
    if proc.returncode == 0:
        assert target.exists()
    else:
        assert proc.returncode == 2 and str(target.parent) in error_line(proc), describe(proc)


def test_out_is_a_file(run_mpipack, tmp_path):
    f = tmp_path / "not-a-folder"
    f.write_text("x")
    proc, _, _ = run_mpipack(2, "two-spheres", extra=["--out", str(f)], timeout=120)
    assert proc.returncode == 2, describe(proc)
    assert "not-a-folder" in error_line(proc)
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("P", [1, 2, 3])
def test_comm_and_partition(tmp_path, P):
    """Fused reductions (NaN wins, Inf kept, exact int sums), exact sums over ranks, the packed
    alltoallv (ragged rows of five dtypes; sparse patterns call after call), the RCB boxes and the ghost layer:
    tests/mpi_scripts/comm_checks.py."""
    proc = mpirun(P, [sys.executable, MPI_SCRIPTS / "comm_checks.py"], cwd=tmp_path)
    assert proc.returncode == 0, describe(proc)
    assert "comm: OK" in proc.stdout, describe(proc)


def test_too_dense_start_is_reported_not_killed(run_mpipack):
    """A Gaussian start far too dense for the pair-row memory budget stops collectively with
    exit 2 and a one-line reason, instead of being killed by the kernel's OOM killer."""
    proc, summary, _ = run_mpipack(2, "paper-2d", ["n=20000", "neighbor.max_pair_gib=0.01"], timeout=120)
    assert proc.returncode == 2, describe(proc)
    line = error_line(proc)
    assert "too dense" in line and "init.sigma" in line and "max_pair_gib" in line, describe(proc)
    assert "Traceback" not in proc.stderr
    assert summary["exit_code"] == 2 and "too dense" in summary["error"], summary
    # the same budget is plenty for a sparse enough start of the same size
    proc, summary, _ = run_mpipack(2, "paper-2d", ["n=20000", "neighbor.max_pair_gib=0.01", "init.sigma=60",
                                             "stop.max_iter=5", "stop.eps=0"], timeout=120)
    assert proc.returncode == 0, describe(proc)
    assert summary["iterations"] == 5
