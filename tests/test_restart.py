"""Checkpoints and restarts through the command line: a run restarted on another number of
ranks continues bit for bit as the uninterrupted run; signals and --walltime stop every rank
at the same iteration with a checkpoint (exit 5); numerical trouble keeps the last good state;
summary.json on every exit; nothing lost when an output fails."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import SIGKILL_TIMEOUT, SIGNAL_GRACE, assert_bitwise_equal, describe, mpi_env, mpipack_run

FIXED = ["stop.rule=eps", "stop.eps=0"]
CASES = {
    # expanding Gaussian start: migrations, rebuilds, far partners on several ranks
    "daha": ["n=300"] + FIXED,
    "fire": ["n=300", "method.schedule=\"fire-al\""] + FIXED,
    # 3D: the penalty factor reaches its cap at iteration ~1240 and the inner solves are
    # L-BFGS's from there (the per-sphere memory migrates and is checkpointed)
    "fire-qn": ["n=200", "dim=3"] + FIXED,
    "nap": ["n=60", "method.name=nap", "method.form=NS", "method.alpha=0.1", "method.beta=0.16",
            "method.l_inner=20"] + FIXED,
}


def run_cli(P, workdir, sets, extra=(), timeout=300):
    workdir.mkdir(parents=True, exist_ok=True)
    return mpipack_run(P, workdir, None, sets, dump=True, extra=extra, timeout=timeout)


@pytest.mark.parametrize("case,total,split,ranks", [
    ("daha", 600, 250, (1, 3)), ("daha", 600, 300, (3, 2)), ("nap", 40, 15, (1, 3)), ("nap", 40, 20, (3, 2)),
    ("fire", 900, 350, (1, 3)), ("fire", 900, 600, (3, 2)),
    ("fire-qn", 2000, 1700, (1, 3)), ("fire-qn", 2000, 1900, (3, 2)),
])
def test_restart_on_other_rank_counts_is_bitwise(tmp_path, case, total, split, ranks):
    sets = CASES[case]
    p_ref, s_ref, d_ref = run_cli(1, tmp_path / "ref", sets + [f"stop.max_iter={total}"])
    assert p_ref.returncode == 0, describe(p_ref)
    first, second = ranks
    p1, s1, _ = run_cli(first, tmp_path / "run", sets + [f"stop.max_iter={split}",
                                                          f"output.checkpoint_every={split}"])
    assert p1.returncode == 0 and s1["checkpoint"]["iteration"] == split, describe(p1)
    p2, s2, d2 = run_cli(second, tmp_path / "run", [f"stop.max_iter={total}"],
                         extra=["--restart", tmp_path / "run" / "out"])
    assert p2.returncode == 0, describe(p2)
    assert s2["iterations"] == total and s2["ranks"] == second and s2["restart_from"]
    assert_bitwise_equal(d_ref, d2, f"{case}: {first} ranks to {split}, then {second} ranks to {total}")
    assert s2["W"] == s_ref["W"]
    if case == "fire-qn":  # the checkpoint was taken in the L-BFGS phase
        assert s_ref["schedule"]["lbfgs_from"] < split, s_ref["schedule"]
        assert s2["schedule"] == s_ref["schedule"]


@pytest.mark.parametrize("split,ranks", [(1, (1, 2)), (2, (2, 3)), (3, (3, 1)), (6, (1, 1)), (9, (2, 2))])
def test_restart_from_the_first_iterations_is_bitwise(tmp_path, split, ranks):
    """A checkpoint that a bound writes in the fire-al schedule's first phase (the start and the
    explosion, whose dual gain changes every iteration) continues bit for bit: the checkpoint
    holds the state as the loop left it, before the final figures update the multipliers."""
    sets = ["n=300", "--seed", "4"]
    p_ref, s_ref, d_ref = run_cli(1, tmp_path / "ref", sets[:1], extra=sets[1:])
    assert p_ref.returncode == 0 and s_ref["converged"], describe(p_ref)
    first, second = ranks
    p1, s1, _ = run_cli(first, tmp_path / "run", [sets[0], f"stop.max_iter={split}"], extra=sets[1:])
    assert p1.returncode == 4 and s1["checkpoint"]["iteration"] == split, describe(p1)
    assert s1["schedule"]["phase"] != "fire" or split > 3, s1["schedule"]
    p2, s2, d2 = run_cli(second, tmp_path / "run", ["stop.max_iter=auto"],
                         extra=["--restart", tmp_path / "run" / "out"])
    assert p2.returncode == 0, describe(p2)
    assert s2["iterations"] == s_ref["iterations"] and s2["W"] == s_ref["W"]
    assert_bitwise_equal(d_ref, d2, f"stopped at {split} on {first} rank(s), continued on {second}")


def test_restart_refuses_a_change_of_physics(tmp_path):
    p1, s1, _ = run_cli(1, tmp_path, ["n=50", "stop.max_iter=20", "output.checkpoint_every=20"] + FIXED)
    assert p1.returncode == 0, describe(p1)
    p2, _, _ = run_cli(1, tmp_path / "again", ["method.alpha=0.01"], extra=["--restart", tmp_path / "out"])
    assert p2.returncode == 2, describe(p2)
    assert "method.alpha" in p2.stderr and "Traceback" not in p2.stderr, describe(p2)


@pytest.mark.parametrize("content", [b"", b"not hdf5 at all", b"\x89HDF\r\n\x1a\n" + b"\0" * 100])
def test_bad_checkpoint_is_one_line_exit_2(tmp_path, content):
    f = tmp_path / "checkpoint.h5"
    f.write_bytes(content)
    p, _, _ = run_cli(2, tmp_path, [], extra=["--restart", f])
    assert p.returncode == 2, describe(p)
    errors = [line for line in p.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "Traceback" not in p.stderr, describe(p)


def long_run(P, out, sets=()):
    args = ["mpirun", "--oversubscribe", "-n", str(P), sys.executable, "-m", "mpipack.cli", "run",
            "--quiet", "--out", str(out), "--set", "n=500", "--set", "stop.max_iter=100000000"]
    for s in list(FIXED) + list(sets):
        args += ["--set", s]
    env = dict(mpi_env(), **{SIGKILL_TIMEOUT: SIGNAL_GRACE})  # a user's grace (tools/env.sh)
    return subprocess.Popen(args, cwd=str(out.parent), env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def signal_long_run(P, out, sig):
    """A long run on P ranks, sent ``sig`` once its first scheduled checkpoint says the loop is
    running; returns (process, the time of the signal, stdout, stderr)."""
    proc = long_run(P, out, ["output.checkpoint_every=200"])
    deadline = time.time() + 120
    while not (out / "checkpoint.h5").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.2)
    time.sleep(1)
    t0 = time.time()
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=120)
    return proc, t0, stdout, stderr


@pytest.mark.parametrize("P", [1, 2, 3])
def test_sigusr1_checkpoints_every_rank_and_exits_5(tmp_path, P):
    out = tmp_path / "out"
    proc, _, stdout, stderr = signal_long_run(P, out, signal.SIGUSR1)
    assert proc.returncode == 5, (proc.returncode, stdout, stderr)
    s = json.loads((out / "summary.json").read_text())
    assert s["exit_code"] == 5 and s["stop_reason"] == "signal"
    assert s["checkpoint"]["iteration"] == s["iterations"] > 0
    assert "Traceback" not in stderr
    if P != 2:
        return
    # the checkpoint continues the run: to the signal's iteration + 10, the same as straight
    total = s["iterations"] + 10
    p2, s2, d2 = run_cli(2, tmp_path / "again", [f"stop.max_iter={total}"], extra=["--restart", out])
    assert p2.returncode == 0, describe(p2)
    p3, s3, d3 = run_cli(1, tmp_path / "straight", ["n=500", f"stop.max_iter={total}"] + FIXED)
    assert_bitwise_equal(d3, d2, "signal checkpoint + restart vs straight")


@pytest.mark.parametrize("P,sig", [(1, signal.SIGTERM), (2, signal.SIGTERM), (3, signal.SIGINT), (2, signal.SIGINT)])
def test_sigterm_or_sigint_to_mpirun_checkpoints_and_writes_the_summary(tmp_path, P, sig):
    """What a scheduler or Ctrl-C does: the signal goes to mpirun, which forwards it to the ranks
    after odls_base_sigkill_timeout seconds (5, tools/env.sh) and kills them as long after. Every
    rank stops at the same iteration with a checkpoint and a summary (exit 5) within that time;
    mpirun itself reports 1 for a job it ended."""
    out = tmp_path / "out"
    proc, t0, stdout, stderr = signal_long_run(P, out, sig)
    assert proc.returncode in (1, 5), (proc.returncode, stdout, stderr)
    s = json.loads((out / "summary.json").read_text())
    assert s["exit_code"] == 5 and s["stop_reason"] == "signal", s
    assert s["checkpoint"]["iteration"] == s["iterations"] > 200
    assert (out / "summary.json").stat().st_mtime - t0 < 10  # within the grace period
    assert "Traceback" not in stderr


def test_walltime_checkpoints_before_the_limit(tmp_path):
    t0 = time.time()
    p, s, _ = run_cli(2, tmp_path, ["n=500", "stop.max_iter=100000000"] + FIXED,
                      extra=["--walltime", "00:00:10"])
    assert p.returncode == 5, describe(p)
    assert time.time() - t0 < 10 + 30  # mpirun's own start and end, on a loaded machine
    # the ranks' own clock: the end of the loop came before the limit, counted from the
    # process's start (the first iteration's age includes the start-up)
    assert s["first_iteration_seconds"] + s["loop_seconds"] < 10, s
    assert s["stop_reason"] == "walltime" and s["checkpoint"]["iteration"] == s["iterations"] > 10


def test_numerical_trouble_keeps_the_last_good_state(tmp_path):
    p, s, _ = run_cli(1, tmp_path, ["n=500", "init.sigma=1.0", "method.beta=1e15", "method.gamma=1.6e-2", "stop.max_iter=2000"])
    assert p.returncode == 3, describe(p)
    assert s["exit_code"] == 3 and "diverges" in s["error"]
    ck = tmp_path / "out" / "checkpoint.h5"
    assert ck.exists() and any(f.endswith("checkpoint.h5") for f in s["files"]), s["files"]
    from mpipack.io.checkpoint import read_checkpoint
    from mpipack.parallel.comm import Comm
    block, scalars, _ = read_checkpoint(Comm(), str(ck))
    import numpy as np
    assert np.all(np.isfinite(block["x"]))


def test_summary_on_every_exit_says_what_ran(tmp_path):
    p, s, _ = run_cli(1, tmp_path, ["n=50", "stop.max_iter=10"] + FIXED)
    assert p.returncode == 0, describe(p)
    for key in ("resolved_scene", "version", "date", "command_line", "ranks", "exit_code", "exit_status"):
        assert key in s, key
    assert s["resolved_scene"]["n"] == 50 and s["exit_code"] == 0 and s["ranks"] == 1


def test_a_failed_output_keeps_the_result(tmp_path):
    p, s, _ = mpipack_run(1, tmp_path, None, ["n=50", "stop.max_iter=10"] + FIXED,
                          extra=["--dump", "/proc/final.npz"])
    assert p.returncode == 0, describe(p)
    assert "the final particles: written to" in p.stderr, describe(p)
    kept = [f for f in s["files"] if f.endswith(".npz")]
    assert kept and os.path.exists(kept[0])


def test_vtk_command(tmp_path):
    p, s, _ = run_cli(2, tmp_path, ["n=100", "stop.max_iter=40", "output.snapshot_every=20"] + FIXED)
    assert p.returncode == 0, describe(p)
    out = tmp_path / "out"
    v = subprocess.run(["mpirun", "--oversubscribe", "-n", "2", sys.executable, "-m", "mpipack.cli", "vtk", str(out)],
                       cwd=str(tmp_path), env=mpi_env(), capture_output=True, text=True, timeout=300)
    assert v.returncode == 0, describe(v)
    import meshio
    vtus = sorted((out / "vtk").glob("snapshot_*.vtu"))
    assert len(vtus) == 3  # iterations 0, 20 and 40 (the start, and the final state is iteration 40)
    assert len(sorted((out / "vtk").glob("contacts_*.vtu"))) == 3  # each snapshot's contact network
    mesh = meshio.read(vtus[-1])
    assert mesh.points.shape == (100, 3)
    assert set(mesh.point_data) >= {"diameter", "pressure", "contacts", "net_force"}
    assert np.all(mesh.point_data["net_force"] >= 0) and mesh.point_data["net_force"].max() > 0
    assert (out / "snapshots.pvd").exists()
    # a truncated snapshot file: one line that names it
    h5 = out / "snapshots.h5"
    h5.write_bytes(h5.read_bytes()[:20000])
    v = subprocess.run([sys.executable, "-m", "mpipack.cli", "vtk", str(out)], cwd=str(tmp_path),
                       env=mpi_env(), capture_output=True, text=True, timeout=120)
    assert v.returncode == 2 and str(h5) in v.stderr and "Traceback" not in v.stderr, describe(v)


def test_coincident_centres_are_separated_the_same_on_any_rank_count(tmp_path):
    """All 50 centres exactly at one point (a state no scene can make): the run moves them apart
    by 1e-6 d in directions drawn from (seed, gid), then expands, bit for bit on 1 and 3 ranks."""
    from mpipack.experiments.suite import one_point_checkpoint
    seed_dir = one_point_checkpoint(str(tmp_path), 50, 2, "S", [])
    dumps = {}
    for P in (1, 3):
        p, s, d = run_cli(P, tmp_path / f"r{P}", ["stop.max_iter=300", "stop.rule=eps", "stop.eps=0"],
                          extra=["--restart", seed_dir])
        assert p.returncode == 0, describe(p)
        assert s["W"] > 1.0, s  # the cloud came apart (W = 0 while every centre coincides)
        dumps[P] = d
    assert_bitwise_equal(dumps[1], dumps[3], "one point: 1 rank vs 3 ranks")


def test_a_run_stopped_by_its_iteration_bound_can_be_continued(tmp_path):
    """Exit 4 at stop.max_iter leaves a checkpoint (nothing computed is lost); restarted with a
    larger bound on another rank count, the run continues bit for bit as one run to that bound
    (certificate history and schedule included)."""
    sets = ["n=300", "seed=2"]
    p_ref, s_ref, d_ref = run_cli(1, tmp_path / "ref", sets + ["stop.max_iter=900"])
    assert p_ref.returncode == 4, describe(p_ref)
    p1, s1, _ = run_cli(1, tmp_path / "run", sets + ["stop.max_iter=400"])
    assert p1.returncode == 4 and s1["checkpoint"]["iteration"] == 400, describe(p1)
    assert "checkpoint" in s1 and os.path.exists(s1["checkpoint"]["path"])
    p2, s2, d2 = run_cli(2, tmp_path / "run", ["stop.max_iter=900"], extra=["--restart", tmp_path / "run" / "out"])
    assert p2.returncode == 4 and s2["iterations"] == 900, describe(p2)
    assert_bitwise_equal(d_ref, d2, "400 iterations on 1 rank, then to 900 on 2")
    assert s2["W"] == s_ref["W"] and s2["certificate"] == s_ref["certificate"]


def test_a_signal_during_a_checks_fit_stops_at_once_and_the_restart_makes_the_check(tmp_path):
    """A stop request that arrives while a certificate check fits its multipliers (thousands of
    steps at large N: seconds to minutes, beyond a scheduler's grace period) ends the fit on every
    rank and the run at once (exit 5, checkpoint of that iteration); the restart makes the check
    first and continues bit for bit as the run never stopped."""
    import mpipack
    from mpipack.engine.hooks import Hook
    from mpipack.stop import signals

    seen = []
    record = Hook(lambda ctx: seen.append((ctx.iteration, ctx.solver.stop_rule.certifier.fit_steps)), every=1)
    scene = dict(seed=0, n=100, dim=3)  # a check of it fits (which one depends on the CPU's code)
    ref = mpipack.run("default", hooks=[record], gather=True, **scene)
    assert ref.converged
    # the decision of iteration `it` ran a fit when the steps grew before the next iteration's
    # hook; the last check's, which the hooks do not see again, when it certified with fitted
    # multipliers (the certificate of a certified stop is that check's own)
    fits = [it for (it, f), (_, f_next) in zip(seen, seen[1:]) if f_next > f]
    if ref.summary["certificate"]["kkt"]["multipliers"] == "fitted":
        fits.append(ref.iterations)
    assert fits, "the reference run fitted no multipliers"
    at = fits[0]

    def signal_at(ctx):
        if ctx.iteration == at:
            signals.request_stop()  # as a handler would, while the iteration's decisions run
    out = str(tmp_path / "run")
    cut = mpipack.run("default", out=out, hooks=[Hook(signal_at, every=1)], **scene)
    assert cut.exit_code == 5 and cut.stop_reason == "signal" and cut.iterations == at, cut.summary
    assert cut.summary["checkpoint"]["iteration"] == at
    again = mpipack.run(restart=out, gather=True)
    assert again.exit_code == 0 and again.iterations == ref.iterations and again.figures["W"] == ref.figures["W"]
    assert_bitwise_equal(ref.particles, again.particles, "signal during a fit, then restart")


def damage(path, dataset, how, keep_checksum):
    """Change one element of a checkpoint's dataset in place (h5py, serial)."""
    import h5py
    with h5py.File(path, "r+") as f:
        d = f[dataset]
        v = d[...]
        flat = v.reshape(-1)
        flat[len(flat) // 2] = how(flat[len(flat) // 2])
        d[...] = v
        if not keep_checksum:  # a file from before the checksums: the state's own checks remain
            del f.attrs["checksums"]


@pytest.mark.parametrize("dataset,how,keep,ranks,words", [
    ("particles/x", lambda v: v + 1e-9, True, 1, "checksum"),           # silent corruption
    ("history/lambda", lambda v: v * 2.0, True, 2, "checksum"),
    ("particles/x", lambda v: np.nan, False, 3, "not finite"),
    ("particles/diam", lambda v: 0.0, False, 2, "not positive"),
    ("history/lambda", lambda v: -1.0, False, 1, "negative"),
    ("history/gid", lambda v: 10 ** 9, False, 3, "outside"),
])
def test_a_damaged_checkpoint_is_refused_in_one_line(tmp_path, dataset, how, keep, ranks, words):
    p1, s1, _ = run_cli(1, tmp_path, ["n=200", "stop.max_iter=60", "output.checkpoint_every=60"] + FIXED)
    assert p1.returncode == 0, describe(p1)
    ck = tmp_path / "out" / "checkpoint.h5"
    damage(str(ck), dataset, how, keep)
    p2, _, _ = run_cli(ranks, tmp_path / "again", ["stop.max_iter=80"], extra=["--restart", ck])
    assert p2.returncode == 2, describe(p2)
    errors = [line for line in p2.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and words in errors[0] and "Traceback" not in p2.stderr, describe(p2)


def test_a_restart_says_what_it_inherits(tmp_path):
    """The checkpoint's scene keeps its stop.* / output.* / neighbor.* settings on a restart; the
    summary lists them (and the --set given now), and a bound already reached is said at once."""
    p1, s1, _ = run_cli(1, tmp_path, ["n=200", "stop.max_iter=5"])
    assert p1.returncode == 4, describe(p1)
    (tmp_path / "again").mkdir()
    (tmp_path / "more").mkdir()
    p2, s2, _ = mpipack_run(1, tmp_path / "again", None, [], extra=["--restart", tmp_path / "out"], quiet=False)
    assert p2.returncode == 4 and "at or beyond stop.max_iter = 5" in p2.stdout, describe(p2)
    r = s2["restart"]
    assert r["iteration"] == 5 and r["inherited"] == {"stop.max_iter": 5} and r["overrides"] == [], r
    p3, s3, _ = mpipack_run(2, tmp_path / "more", None, ["stop.max_iter=auto"], extra=["--restart", tmp_path / "out"])
    assert p3.returncode == 0, describe(p3)
    assert s3["restart"]["overrides"] == ["stop.max_iter"] and s3["restart"]["inherited"] == {}, s3["restart"]
