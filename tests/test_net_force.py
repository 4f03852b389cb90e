"""The per-sphere net force |g_i| (the sphere's row of the KKT residual) in the snapshots, the
same bits on 1, 2 and 3 ranks, and tools/net_force_map.py, which reads it back."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import describe, mpipack_run

TOOLS = Path(__file__).resolve().parents[1] / "tools"
sys.path.insert(0, str(TOOLS))
import net_force_map  # noqa: E402

# the default scene, stopped before it certifies (fire-al: the force multipliers), snapshots
# at 200 and 400
SETS = ["n=300", "stop.max_iter=400", "output.snapshot_every=200"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = {}
    for P in (1, 2, 3):
        work = tmp_path_factory.mktemp(f"net{P}")
        proc, summary, _ = mpipack_run(P, work, None, SETS, timeout=300)
        assert proc.returncode == 4, describe(proc)
        out[P] = (work / "out" / "snapshots.h5", summary)
    return out


def test_net_force_is_the_kkt_residual_per_sphere_on_1_2_3_ranks(runs):
    from mpipack.io.snapshots import list_snapshots, read_snapshot
    path1, summary1 = runs[1]
    assert list_snapshots(str(path1)) == [0, 200, 400]  # the start, the schedule
    f1, a1 = read_snapshot(str(path1), 400)
    g = f1["net_force"]
    assert g.shape == (300,) and np.all(g >= 0) and g.max() > 0
    # the field rebuilds the snapshot's KKT residual (the run's multipliers) and the summary's
    kkt, counts = net_force_map.spread(g, float(((f1["position"] - f1["position"].mean(0)) ** 2).sum()))
    assert kkt == pytest.approx(a1["kkt_residual"], rel=1e-9)
    assert kkt == pytest.approx(summary1["kkt_residual_run"], rel=1e-9)
    assert summary1["max_net_force"] == g.max()
    assert summary1["net_force_share"] == pytest.approx(g.max() ** 2 / (g.astype(float) ** 2).sum(), rel=1e-9)
    assert 1 <= counts[0.5] <= counts[0.9] <= counts[0.99] <= 300
    for P in (2, 3):
        fP, _ = read_snapshot(str(runs[P][0]), 400)
        assert np.array_equal(fP["net_force"], g), f"net_force on {P} ranks differs from 1 rank"
        assert runs[P][1]["net_force_share"] == summary1["net_force_share"]


def test_spread_counts_the_spheres_that_carry_the_residual():
    g = np.array([3.0, 0.0, 1.0, 1.0, 1.0])  # squares 9, 0, 1, 1, 1: total 12
    kkt, counts = net_force_map.spread(g, 48.0)
    assert kkt == pytest.approx(0.5)
    assert counts == {0.5: 1, 0.9: 3, 0.99: 4}  # 9/12 = 0.75, 10/12, 11/12 = 0.917, 12/12
    assert net_force_map.spread(np.zeros(3), 1.0) == (0.0, {0.5: 0, 0.9: 0, 0.99: 0})


def test_cli_reports_and_draws(runs, tmp_path):
    path, _ = runs[2]
    png = tmp_path / "map.png"
    proc = subprocess.run([sys.executable, str(TOOLS / "net_force_map.py"), str(path), "--from", "200",
                           "--png", str(png)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "iteration 400, N = 300: KKT residual" in proc.stdout
    assert "of the squared residual (of 300)" in proc.stdout
    assert "moved since iteration 200: median" in proc.stdout
    assert png.stat().st_size > 10000
