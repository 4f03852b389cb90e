"""Shared helpers: run mpipack (or a test script) under ``mpirun`` with a self-contained env.

The tests do not rely on the caller having sourced tools/env.sh: the environment for every
subprocess is `mpipack.parallel.launcher.mpi_env`: os.environ plus what Open MPI needs to run as root and with
more ranks than cores. Every subprocess has a timeout, so a hang fails instead of blocking.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent
MPI_SCRIPTS = TESTS / "mpi_scripts"

# arrays of an ``mpipack run --dump`` file
DUMP_KEYS = ("gid", "x", "x_prev", "diam", "pairs_gid", "pairs_lambda")

# generous: a healthy run of any test command takes a few seconds
TIMEOUT = 300


# the environment of every subprocess: the one `mpipack suite` builds for its runs (root,
# oversubscription, yield when idle, this checkout first on PYTHONPATH)
from mpipack.parallel.launcher import mpi_env

# mpirun ends a job any rank of which exits non-zero (2, 3, 4, 5: most test runs) the way it
# ends one on SIGTERM: it waits odls_base_sigkill_timeout seconds, signals the ranks (gone by
# then), waits as long again -- 10.4 s with tools/env.sh's 5 s for a rank that exits 4 at once,
# 2.4 s with Open MPI's own 1 s, 0.5 s for exit 0. The tests' small runs take Open MPI's 1 s;
# the tests of a signal to mpirun, and the Slurm jobs, keep the users' 5 s (SIGNAL_GRACE).
SIGKILL_TIMEOUT = "OMPI_MCA_odls_base_sigkill_timeout"
SIGNAL_GRACE = "5"
os.environ[SIGKILL_TIMEOUT] = "1"


def mpirun(n, args, cwd, timeout=TIMEOUT):
    """``mpirun -n n <args>`` with output captured; returns CompletedProcess (never raises on
    a non-zero exit; raises subprocess.TimeoutExpired on a hang)."""
    cmd = ["mpirun", "--oversubscribe", "-n", str(n)] + [str(a) for a in args]
    return subprocess.run(cmd, cwd=str(cwd), env=mpi_env(), capture_output=True, text=True,
                          timeout=timeout)


def describe(proc):
    """A failure message with the command, exit code and captured output."""
    cmd = proc.args if isinstance(proc.args, str) else " ".join(map(str, proc.args))
    return (f"\n$ {cmd}\nexit code {proc.returncode}\n--- stdout ---\n{proc.stdout}"
            f"\n--- stderr ---\n{proc.stderr}")


def mpipack_run(n_ranks, workdir, scene=None, sets=(), dump=False, extra=(), timeout=TIMEOUT,
                quiet=True):
    """Run ``mpipack run`` on n_ranks ranks in workdir (output folder workdir/out).

    Returns (proc, summary dict or None, dump dict or None).
    """
    workdir = Path(workdir)
    out = workdir / "out"
    args = [sys.executable, "-m", "mpipack.cli", "run"]
    if scene is not None:
        args.append(scene)
    for s in sets:
        args += ["--set", s]
    args += ["--out", out]
    if quiet:
        args.append("--quiet")
    dump_path = workdir / "final.npz"
    if dump:
        args += ["--dump", dump_path]
    args += list(extra)
    proc = mpirun(n_ranks, args, cwd=workdir, timeout=timeout)
    summary = None
    if (out / "summary.json").exists():
        summary = json.loads((out / "summary.json").read_text())
    data = None
    if dump and dump_path.exists():
        with np.load(dump_path) as z:
            data = {k: z[k] for k in z.files}
    return proc, summary, data


@pytest.fixture
def run_mpipack(tmp_path):
    """run_mpipack(n_ranks, scene=None, sets=(), dump=False, extra=(), tag=None, timeout=...,
    quiet=True): mpipack_run in a fresh sub-folder of tmp_path."""
    counter = {"k": 0}

    def _run(n_ranks, scene=None, sets=(), dump=False, extra=(), tag=None, timeout=TIMEOUT,
             quiet=True):
        counter["k"] += 1
        d = tmp_path / (tag or f"run{counter['k']}-np{n_ranks}")
        d.mkdir(parents=True, exist_ok=True)
        return mpipack_run(n_ranks, d, scene=scene, sets=sets, dump=dump, extra=extra,
                           timeout=timeout, quiet=quiet)

    return _run


def assert_bitwise_equal(ref, other, what):
    assert set(ref) == set(DUMP_KEYS) and set(other) == set(DUMP_KEYS), (sorted(ref), sorted(other))
    for k in DUMP_KEYS:
        a, b = ref[k], other[k]
        assert a.dtype == b.dtype and a.shape == b.shape, (what, k, a.dtype, b.dtype, a.shape, b.shape)
        if not np.array_equal(a, b):
            bad = np.argwhere(a != b) if a.shape == b.shape else None
            pytest.fail(f"{what}: '{k}' differs bitwise at {len(bad)} entries, first {bad[:3].tolist()}; "
                        f"max |diff| {np.max(np.abs(a.astype(float) - b.astype(float)))}")


def step_each(s, n, fn):
    """Advance Solver ``s`` by n iterations through the one loop (engine.loop.run, stop rule: n more
    iterations), calling fn(figures) after each. Returns run's result dict.

    Tests observe the trajectory through a hook, as any other user of the loop does."""
    from mpipack.engine import hooks, loop
    scene = s.scene.replace(stop={"eps": 0.0, "max_iter": s.state.iteration + n})
    _, res = loop.run(scene, s.comm, hooks=[hooks.Hook(lambda ctx: fn(ctx.figures), every=1)],
                            solver=s)
    return res


# ---- markers -------------------------------------------------------------------------------
# tests of 3 s or more on this 2-core machine (pytest --durations=0, the whole suite,
# 2026-11-27): the fast lane, pytest -m "not slow", leaves them out (about 3 minutes instead of
# 13); CI runs everything. The Slurm tests mark themselves (tests/test_jobs.py).
SLOW = {
    "tests/test_container_files.py::test_a_run_writes_it_once_and_overwrite_removes_it",
    "tests/test_container_files.py::test_view_py_renders_the_run_with_its_container",
    "tests/test_post_container.py::test_a_real_container_run_the_same_on_1_2_3_ranks",
    "tests/test_container.py::test_the_same_packing_on_1_2_3_ranks",
    "tests/test_container.py::test_restart_onto_another_rank_count",
    "tests/test_api.py::test_keyword_overrides_and_options",
    "tests/test_api.py::test_the_readme_example_runs_on_any_rank_count",
    "tests/test_bench_phases.py::test_the_packed_state_is_the_same_on_any_rank_count",
    "tests/test_check.py::test_two_sphere_verdict_against_runs",
    "tests/test_compare.py::test_compare_quick",
    "tests/test_compare.py::test_compare_with_a_peer_curve",
    "tests/test_comm_counts.py::test_counting_changes_no_result",
    "tests/test_convergence.py::test_a_run_that_cannot_certify_says_why",
    "tests/test_convergence.py::test_defaults_certify",
    "tests/test_convergence.py::test_the_schedule_does_not_depend_on_the_length_unit",
    "tests/test_convergence_sweep.py::test_a_run_beyond_the_timeout_stops_itself_with_its_figures",
    "tests/test_convergence_sweep.py::test_a_run_that_does_not_stop_itself_is_reported_as_killed",
    "tests/test_io.py::test_checkpoint_survives_a_rank_killed_mid_write",
    "tests/test_io.py::test_snapshots_by_gid",
    "tests/test_kernels_fire.py::test_fire_kernel_matches_reference",
    "tests/test_least_kkt_trace.py::test_long_fits_bound_the_run_and_each_other",
    "tests/test_metrics.py::test_force_imbalance_is_the_net_force_over_the_contact_forces",
    "tests/test_metrics.py::test_metrics_rows_approach_the_optimum_and_are_rank_independent",
    "tests/test_metrics.py::test_the_certificate_uses_the_force_multipliers_of_pairs_in_contact",
    "tests/test_nested.py::test_same_bits_on_1_2_3_ranks",
    "tests/test_net_force.py::test_net_force_is_the_kkt_residual_per_sphere_on_1_2_3_ranks",
    "tests/test_pair_store.py::test_pairs_survive_migration_on_1_2_3_ranks",
    "tests/test_paper.py::test_paper_quick_report",
    "tests/test_parallel.py::test_bad_scene_file_exits_2",
    "tests/test_parallel.py::test_certified_by_fitted_multipliers_on_1_2_3_ranks",
    "tests/test_parallel.py::test_default_scene_converges_on_2_ranks",
    "tests/test_parallel.py::test_same_bits_on_1_2_3_ranks",
    "tests/test_parallel.py::test_shortened_lbfgs_steps_same_bits_on_1_2_3_ranks",
    "tests/test_peers_side.py::test_a_chained_ladder_passes_through_the_same_states",
    "tests/test_restart.py::test_a_run_stopped_by_its_iteration_bound_can_be_continued",
    "tests/test_restart.py::test_coincident_centres_are_separated_the_same_on_any_rank_count",
    "tests/test_restart.py::test_restart_on_other_rank_counts_is_bitwise",
    "tests/test_restart.py::test_restart_refuses_a_change_of_physics",
    "tests/test_restart.py::test_sigusr1_checkpoints_every_rank_and_exits_5",
    "tests/test_restart.py::test_walltime_checkpoints_before_the_limit",
    "tests/test_suite.py::test_quick_suite",
    "tests/test_watchdog.py::test_a_restart_keeps_the_watchdogs_count",
    "tests/test_watchdog.py::test_aha_s_cycle_exits_3_on_any_rank_count",
    "tests/test_watchdog.py::test_the_watchdog_can_be_turned_off",
    "tests/test_post.py::test_a_real_run_in_its_known_ranges_on_1_2_3_ranks",
    "tests/test_distributions.py::test_the_same_packing_on_1_2_3_ranks",
    "tests/test_post.py::test_fcc_file_gives_the_same_numbers_on_1_2_3_ranks",
    "tests/test_post.py::test_an_unconverged_snapshot_is_flagged",
    "tests/test_post.py::test_convergence_and_compare",
    "tests/test_paraview.py::test_runs_write_the_start_first_the_same_on_1_2_3_ranks_and_a_restart_keeps_it",
    "tests/test_paraview.py::test_radius_start_and_pairs_the_same_on_1_2_3_ranks",
    "tests/test_paraview.py::test_view_py_renders_a_picture",
    "tests/test_paraview.py::test_pvpython_sees_radius_pressure_and_the_contacts_with_lambda",
}
# a test that launches mpirun (through these helpers or itself) is an MPI test
MPI_WORDS = ("mpirun", "mpipack_run", "run_mpipack", "run_cli(", "long_run(", "mpi_script")


def pytest_collection_modifyitems(config, items):
    import inspect
    for item in items:
        base = item.nodeid.split("[")[0]
        if base in SLOW:
            item.add_marker(pytest.mark.slow)
        try:
            source = inspect.getsource(item.function)
        except (OSError, TypeError):
            continue
        if any(w in source for w in MPI_WORDS):
            item.add_marker(pytest.mark.mpi)
