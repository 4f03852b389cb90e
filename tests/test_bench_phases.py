"""``mpipack bench --phases --quick``: every phase of a default run in the table and in valid
JSON, the byte counts where the docstring gives them, and the packed state it times written
the same on 1, 2 and 3 ranks (no timing is asserted)."""

import json
import math
import sys

import numpy as np
import pytest

from conftest import describe, mpirun
from mpipack.experiments.bench import PHASE_ORDER, traffic_bytes

N = 100
ARGS = ["-m", "mpipack.cli", "bench", "--phases", "--quick", "--dim", "2", "--n", str(N), "--run-iters", "60"]


def bench(ranks, tmp_path):
    out = tmp_path / f"r{ranks}"
    out.mkdir()
    proc = mpirun(ranks, [sys.executable] + ARGS + ["--json", out / "phases.jsonl", "--state-out", out / "packed"],
                  cwd=out, timeout=300)
    assert proc.returncode == 0, describe(proc)
    return proc, out


def test_quick_phases_print_every_phase_and_valid_json(tmp_path):
    proc, out = bench(1, tmp_path)
    table = {line.split()[0] for line in proc.stdout.splitlines() if line.strip()}
    for name in PHASE_ORDER:
        assert name in table, (name, describe(proc))
    rows = [json.loads(line) for line in (out / "phases.jsonl").read_text().splitlines() if line.strip()]
    assert len(rows) == 1
    r = rows[0]
    assert (r["dim"], r["n"], r["ranks"]) == (2, N, 1)
    assert r["state"]["iterations"] == 60 and r["state"]["stop_reason"] == "max_iter"
    assert r["triad_mb_per_s"] > 0 and len(r["load_average"]) == 3
    assert set(r["phases"]) == set(PHASE_ORDER)
    for name in PHASE_ORDER:
        assert math.isfinite(r["phases"][name]["ns_per_sphere"]), name
    # the traffic model: bytes per sphere from the counts of the docstring
    for name, (sphere, entry, contact) in traffic_bytes(2, r["lbfgs_memory"]).items():
        p = r["phases"][name]
        want = sphere + entry * r["entries_per_sphere"] + contact * r["contact_rows_per_sphere"]
        assert p["bytes_per_sphere"] == pytest.approx(want), name
        assert p["bandwidth_fraction"] == pytest.approx(p["mb_per_s"] * 1e6 / (r["triad_mb_per_s"] * 1e6))
    got = np.load(out / f"packed-2d-n{N}.npz")
    assert got["x"].shape == (N, 2) and got["diam"].shape == (N,)


def test_the_packed_state_is_the_same_on_any_rank_count(tmp_path):
    """The state the phases are timed on is a real run's: bitwise the same on 1, 2, 3 ranks."""
    _, one = bench(1, tmp_path)
    a = np.load(one / f"packed-2d-n{N}.npz")
    for ranks in (2, 3):
        proc, many = bench(ranks, tmp_path)
        rows = [json.loads(line) for line in (many / "phases.jsonl").read_text().splitlines() if line.strip()]
        assert len(rows) == 1 and rows[0]["ranks"] == ranks, describe(proc)
        assert set(rows[0]["phases"]) == set(PHASE_ORDER)
        b = np.load(many / f"packed-2d-n{N}.npz")
        assert np.array_equal(a["x"], b["x"]) and np.array_equal(a["diam"], b["diam"])


@pytest.mark.parametrize("form", ["S", "NS"])
@pytest.mark.parametrize("dim", [2, 3])
def test_a_dual_step_of_gain_zero_changes_no_bit(dim, form):
    """The fire-al kernel skips the multipliers' write-back when beta = 0 (the speed-up the
    phases' profile found): the same bits as the dual step it replaces, lambda + 0 = lambda,
    whether the pass is asked to update lambda or not."""
    from mpipack.kernels import fire as kernels_fire
    from mpipack.parallel import exactsum, neighbors
    from support import CENTRE, no_walls, random_cloud, random_lambda, rows_complete

    rng = np.random.default_rng(7 + dim)
    n = 40
    x, diam = random_cloud(rng, n, dim)
    x_prev = x + 0.05 * rng.normal(size=x.shape)
    lam_full = random_lambda(rng, form, x, diam)
    gid = rng.permutation(n).astype(np.int64)
    offsets, pair_j = rows_complete(n, n, gid)
    owner = np.repeat(np.arange(n), np.diff(offsets))
    lam0 = lam_full[owner, pair_j].copy()
    xbar = x.mean(axis=0)
    kern = kernels_fire.fire_al_step(form, dim)
    out = []
    for update in (True, False):
        for weighted in (True, False):
            lam = lam0.copy()
            x_new = np.full_like(x, np.nan)
            acc = exactsum.new_accumulator(dim + kernels_fire.N_ACC)
            maxima = np.zeros(kernels_fire.N_MAX)
            mirror = neighbors.find_mirrors(n, gid, offsets, pair_j)
            pairs = kernels_fire.pair_work(dim, n, offsets, pair_j, lam, mirror, max_row=math.inf)
            active = kern(x, x_prev, x_new, n, diam, offsets, pair_j, lam, pairs, *no_walls(n), xbar, CENTRE, 1.2, -0.2,
                          0.02, 0.08, 0.0, 0.7, True, weighted, 0.05, update, acc, maxima, False)
            out.append((x_new, lam, acc, maxima, active))
    # the old arithmetic of the dual step with beta = 0, in numpy: max(0, lam + 0 * w * phi)
    assert np.array_equal(np.maximum(0.0, lam0 + 0.0 * lam0), lam0)
    for x_new, lam, acc, maxima, active in out:
        assert np.array_equal(lam, lam0)
        assert np.array_equal(x_new, out[0][0]) and np.array_equal(acc, out[0][2])
        assert np.array_equal(maxima, out[0][3]) and active == out[0][4]
