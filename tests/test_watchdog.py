"""The watchdog: divergence and no progress detected within a bounded number of iterations,
never on a converging run; the verdict is collective (the same iteration on 1, 2 and 3 ranks),
exits 3 with the last state checkpointed, and survives a restart."""

import json
import math
import sys

import pytest

from conftest import describe
from mpipack.stop import watchdog as wd
from mpipack.stop.watchdog import BLOCK, STALL_BLOCKS, Watchdog
from mpipack.stop import rule


def feed(dog, figures, lam=lambda it: 1.0, settled=lambda it: math.inf, start=1):
    """Feed figures(it) -> (relative change, max overlap, W) for it = start, start + 1, ...;
    returns (iteration, kind, message) of the first verdict, or None."""
    for it, (r, o, w) in enumerate(figures, start=start):
        dog.observe({"relative_change": r, "max_overlap": o, "W": w})
        if dog.due(it):
            v = dog.block_end(it, lam(it), settled(it))
            if v:
                return (it,) + v
    return None


def dog(stall=True):
    return Watchdog(n=100, r_natural=10.0, lam_bar=1.0, overlap_tol=1e-3, stall=stall, advice="ADVICE")


def cycle(n, period=37):
    """A periodic orbit: every figure repeats with the period."""
    for it in range(n):
        ph = math.sin(2 * math.pi * it / period)
        yield 1e-3 * (2 + ph), 0.05 * (1 + ph), 3000.0 + 10 * ph


def test_a_cycle_is_stopped_within_the_bound():
    v = feed(dog(), cycle(20 * BLOCK))
    assert v is not None and v[1] == "stalled", v
    assert v[0] <= (STALL_BLOCKS + 1) * BLOCK, v
    assert "no progress" in v[2] and "ADVICE" in v[2]


def test_a_cycle_runs_on_when_the_scene_asked_for_its_iterations():
    assert feed(dog(stall=False), cycle(20 * BLOCK)) is None


@pytest.mark.parametrize("rate", [0.999, 0.9998])  # x0.78 and x0.95 per block
def test_a_linearly_converging_run_is_never_stopped(rate):
    """Slow convergence (5% per block) still counts: the reference moves only on a 10% gain."""
    figs = ((1e-2 * rate ** it * (1.5 + math.sin(it)), 0.2 * rate ** it, 3000 + 100 * rate ** it)
            for it in range(60 * BLOCK))
    assert feed(dog(), figs) is None


def test_a_falling_cloud_is_progress():
    """No contacts, a constant relative change: W falling is the progress."""
    figs = ((1e-3, 0.0, 1e6 * 0.9995 ** it + 3000) for it in range(30 * BLOCK))
    assert feed(dog(), figs) is None


def test_growing_w_is_divergence():
    w_nat = 0.5 * 100 * 10.0 ** 2
    figs = ((1e-2, 0.0, w_nat * 2 ** (it / 100)) for it in range(40 * BLOCK))
    v = feed(dog(), figs)
    assert v is not None and v[1] == "diverged" and "W grew" in v[2], v
    # detected once W passes 10 x its natural size and has grown 3 blocks in a row, or blown out
    assert v[0] <= 15 * BLOCK


def test_growing_multipliers_are_divergence_unless_the_cloud_is_falling():
    steady = ((1e-3 * (2 + math.sin(it)), 0.01, 3000.0) for it in range(20 * BLOCK))
    v = feed(dog(), steady, lam=lambda it: 2.0 ** (it / 100), settled=lambda it: 1e-5)
    assert v is not None and v[1] == "diverged" and "multiplier" in v[2], v
    # a cloud still falling (its W not settled) grows contacts and multipliers: no verdict
    falling = ((1e-3, 0.01, 3e5 * 0.9999 ** it) for it in range(8 * BLOCK))
    assert feed(dog(), falling, lam=lambda it: 2.0 ** (it / 100), settled=lambda it: 2e-3) is None


def test_a_packing_coming_apart_is_divergence():
    """The overlap was 1e-4 and grows x2.8 per block at a steady W: the contacts are unstable."""
    figs = ((1e-3 * (2 + math.sin(it)), 1e-4 if it < 4 * BLOCK else 1e-4 * 2 ** ((it - 4 * BLOCK) / 160), 3000.0)
            for it in range(20 * BLOCK))
    v = feed(dog(), figs, settled=lambda it: 1e-5)
    assert v is not None and v[1] == "diverged" and "overlap" in v[2], v
    # the same rise while W still moves (contacts forming in a falling cloud): no verdict
    figs = ((1e-3, 3e-4 * 2 ** (it / 160), 3e5 * 0.9999 ** it) for it in range(6 * BLOCK))
    assert feed(dog(), figs, settled=lambda it: 2e-3) is None


def test_a_blown_out_cloud_is_divergence():
    figs = ((1e-3, 0.0, 0.5 * 100 * (200 * 10.0) ** 2) for it in range(2 * BLOCK))
    v = feed(dog(), figs)
    assert v is not None and v[0] == BLOCK and "blown out" in v[2], v


def test_save_and_restore_take_the_same_decision():
    figs = list(cycle(20 * BLOCK))
    whole = feed(dog(), figs)
    a = dog()
    assert feed(a, figs[:5 * BLOCK + 17]) is None
    b = dog()
    b.restore(json.loads(json.dumps(a.save())))
    rest = feed(b, figs[5 * BLOCK + 17:], start=5 * BLOCK + 18)
    assert rest is not None and rest == whole


# ---- real runs ----------------------------------------------------------------------------------
AHA_S_CYCLE = ['method.name="aha"', 'method.form="S"', "method.alpha=0.35", "method.beta=1.4",
               "stop.max_iter=20000", "output.snapshots=false"]


def test_aha_s_cycle_exits_3_on_any_rank_count(run_mpipack):
    """AHA-S on two spheres: the contact rings forever (the paper's Fig. 2); the run stops with
    exit 3 at the same iteration on 1, 2 and 3 ranks (3: an empty rank), long before max_iter,
    and leaves a checkpoint of its last state."""
    stopped_at = set()
    for ranks in (1, 2, 3):
        proc, s, _ = run_mpipack(ranks, "two-spheres", AHA_S_CYCLE, timeout=180)
        assert proc.returncode == 3, describe(proc)
        assert proc.stderr.count("no progress toward a packing") == 1 and "AHA has no damping" in proc.stderr, \
            describe(proc)
        assert "Traceback" not in proc.stderr and "aborted" not in proc.stderr, describe(proc)
        assert s["trouble"] == "stalled" and s["exit_code"] == 3
        assert STALL_BLOCKS * BLOCK <= s["iterations"] <= 2 * STALL_BLOCKS * BLOCK, s["iterations"]
        assert s["checkpoint"]["iteration"] == s["iterations"]
        stopped_at.add(s["iterations"])
    assert len(stopped_at) == 1, stopped_at


def test_the_watchdog_can_be_turned_off(run_mpipack):
    proc, s, _ = run_mpipack(1, "two-spheres", AHA_S_CYCLE[:-2] + ["stop.max_iter=5000", "stop.watchdog=false"],
                             timeout=180)
    assert proc.returncode == 4 and s["iterations"] == 5000, describe(proc)


def test_a_restart_keeps_the_watchdogs_count(run_mpipack, tmp_path):
    """Stopped at 2000 and continued: the verdict comes at the same iteration as in one run."""
    proc, whole, _ = run_mpipack(1, "two-spheres", AHA_S_CYCLE, tag="whole")
    assert proc.returncode == 3, describe(proc)
    proc, s, _ = run_mpipack(1, "two-spheres", AHA_S_CYCLE[:-2] + ["stop.max_iter=2100", "output.checkpoint_every=2100"],
                             tag="first")
    assert proc.returncode == 4, describe(proc)
    proc, s, _ = run_mpipack(2, None, ["stop.max_iter=20000"], tag="second",
                             extra=["--restart", str(tmp_path / "first" / "out")])
    assert proc.returncode == 3 and s["iterations"] == whole["iterations"], describe(proc)


def test_fire_al_runs_are_not_stopped_for_slowness():
    """Under fire-al only divergence is watched (its slow phases look like no progress)."""
    from mpipack import config
    from mpipack.engine import solver
    from mpipack.parallel.comm import Comm
    from mpi4py import MPI
    scene = config.load(None, ["n=50", "output.progress_every=0"])
    s = solver.Solver(scene, Comm(MPI.COMM_SELF))
    s.initialise()
    assert not rule.make_watchdog(s, scene).stall
    scene = config.load("paper-2d", ["n=50"])
    s = solver.Solver(scene, Comm(MPI.COMM_SELF))
    s.initialise()
    assert rule.make_watchdog(s, scene).stall
    assert rule.make_watchdog(s, scene.replace(stop={"watchdog": False})) is None
    assert not rule.make_watchdog(s, scene.replace(stop={"eps": 0.0})).stall
    assert wd.STALL_BLOCKS * wd.BLOCK == 3000
