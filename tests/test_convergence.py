"""The default parameters certify at small N (the fire-al schedule; long measurements are in
tools/convergence_sweep.py and docs/research/convergence.md), and a run that cannot certify says which
criterion failed and exits 4. Every run is a real command-line run, checked from its dump."""

import csv

import pytest

from conftest import describe, mpipack_run
from support import brute_force_figures

CERTIFIES = {
    # N, dim, form; sigma "auto" and nothing else set: the defaults
    "2d-S": ["n=100"],
    "2d-NS": ["n=100", "method.form=NS"],
    "1d-S": ["n=50", "dim=1"],
    # disordered packings: the penalty grows until the contact network holds
    "3d-S": ["n=50", "dim=3"],
    "3d-NS": ["n=100", "dim=3", "method.form=NS"],
    "2d-mixed-sizes": ["n=100", "particles.diameter_max=2"],
}


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("case", list(CERTIFIES))
def test_defaults_certify(tmp_path, case, seed):
    proc, s, d = mpipack_run(1, tmp_path, None, CERTIFIES[case] + [f"seed={seed}", "stop.max_iter=20000",
                                                                 "output.snapshots=false"], dump=True)
    assert proc.returncode == 0, describe(proc)
    assert s["converged"] and s["stop_reason"] == "certified", s["certificate"]
    assert s["method"] == "daha" and s["parameters"]["schedule"] == "fire-al"
    cert = s["certificate"]
    assert cert["overlap"]["value"] <= 1e-3 and cert["kkt"]["value"] <= 1e-2 and cert["settled"]["value"] <= 1e-4
    # the overlap, recomputed from the gathered positions
    assert brute_force_figures(d)[1] <= 1e-3
    assert s["schedule"]["phase"] == "fire"


# the fewest spheres: in 3D these seeds never certified (100000 iterations) while the L-BFGS
# phase's gradient step, shortened by the trust region, flung a sphere into a stiff contact and
# back forever, untested (``qn.LBFGS.direction``); the 2D ones certified
TINY = [(2, 3, 0), (3, 3, 5), (5, 3, 0), (5, 3, 7), (2, 2, 0), (3, 2, 0), (5, 2, 0)]


@pytest.mark.parametrize("n,dim,seed", TINY)
def test_the_fewest_spheres_certify(tmp_path, n, dim, seed):
    proc, s, d = mpipack_run(1, tmp_path, None, [f"n={n}", f"dim={dim}", f"seed={seed}", "stop.max_iter=20000",
                                                 "output.snapshots=false"], dump=True)
    assert proc.returncode == 0, describe(proc)
    assert s["converged"] and s["stop_reason"] == "certified", s["certificate"]
    assert brute_force_figures(d)[1] <= 1e-3


@pytest.mark.parametrize("ranks,seed", [(1, 1), (1, 4), (2, 4), (3, 1)])
def test_one_sphere_is_a_packing(tmp_path, ranks, seed):
    """N = 1: W is 0 up to rounding (-0.0 and below were a math domain error in the schedule);
    the run certifies at once on any rank count (two of three ranks own nothing)."""
    proc, s, d = mpipack_run(ranks, tmp_path, None, ["n=1", f"seed={seed}", "output.snapshots=false"], dump=True)
    assert proc.returncode == 0, describe(proc)
    assert s["converged"] and s["max_overlap"] == 0.0 and d["x"].shape == (1, 2)


def test_a_run_that_cannot_certify_says_why(tmp_path):
    """A run whose iteration bound comes before its certificate (3D N = 100 seed 0 certifies
    at 3400, no 3D N = 100 run in 10 seeds before 1600): exit 4, 'not converged', and the
    criteria that failed named on screen and in the summary."""
    proc, s, _ = mpipack_run(1, tmp_path, None, ["n=100", "dim=3", "seed=0", "stop.max_iter=500",
                                                 "output.snapshots=false"], quiet=False)
    assert proc.returncode == 4, describe(proc)
    assert s["converged"] is False and s["stop_reason"] == "max_iter" and s["exit_code"] == 4
    failed = [k for k, c in s["certificate"].items() if not c["ok"]]
    assert failed, s["certificate"]
    assert "NOT" in proc.stdout and "converged" in proc.stdout, describe(proc)


@pytest.mark.parametrize("form", ["S", "NS"])
def test_the_schedule_does_not_depend_on_the_length_unit(tmp_path, form):
    """The penalty, the dual gains and the explosion's weights carry the units of phi (d^2 for
    S, d for NS): a scene scaled by a power of two is the same run, scaled (W times the scale
    squared, overlaps relative to d equal), and a scene in small units (d = 0.01, once a run
    that never separated) certifies. The exact sums resolve 2^-78 absolutely, not relative to
    the scene, so the two runs differ in the last bit of W from the first iterations; FIRE's
    restarts amplify that after ~200 iterations, so the trajectories are compared over the first
    150 and the packings by their quality."""
    base = ["n=300", f"method.form={form}", "seed=1", "stop.max_iter=20000", "output.snapshots=false",
            "output.metrics_every=10"]
    runs, curves = {}, {}
    for d in (1.0, 1024.0, 0.01):
        (tmp_path / str(d)).mkdir()
        proc, s, _ = mpipack_run(1, tmp_path / str(d), None, base + [f"particles.diameter={d}"])
        assert proc.returncode == 0, describe(proc)
        assert s["converged"] and s["stop_reason"] == "certified", (d, s["certificate"])
        runs[d] = s
        with open(tmp_path / str(d) / "out" / "metrics.csv") as f:
            curves[d] = {int(r["iteration"]): (float(r["W"]), float(r["max_overlap"])) for r in csv.DictReader(f)}
    early = [it for it in curves[1.0] if it <= 150]
    assert len(early) == 15
    for it in early:
        (w1, ov1), (wk, ovk) = curves[1.0][it], curves[1024.0][it]
        assert wk == pytest.approx(w1 * 1024.0 ** 2, rel=1e-10), it
        assert ovk == pytest.approx(ov1, rel=1e-10, abs=1e-14), it
    for d in (1024.0, 0.01):
        assert runs[d]["W"] / d ** 2 == pytest.approx(runs[1.0]["W"], rel=0.02), d
