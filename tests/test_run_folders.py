"""A run never writes into a folder that holds another run (issue: a rerun in the same folder
crashed on another N and appended to the old snapshots on the same N). ``--restart`` alone
continues a run in place; an explicit --out holding another run is refused in one line unless
--overwrite; the default folder is numbered. The decision is rank 0's, broadcast: 1, 2, 3 ranks."""

import json

import pytest

from conftest import describe, mpirun

RUN = ["-m", "mpipack.cli", "run", "--quiet"]


def run(tmp_path, ranks, *args):
    import sys
    return mpirun(ranks, [sys.executable] + RUN + [str(a) for a in args], tmp_path, timeout=300)


def summary(folder):
    return json.loads((folder / "summary.json").read_text())


@pytest.mark.parametrize("ranks", [1, 2, 3])
def test_an_explicit_folder_holding_a_run_is_refused_and_kept(tmp_path, ranks):
    out = tmp_path / "A"
    first = run(tmp_path, 1, "--set", "n=50", "--seed", "1", "--out", out)
    assert first.returncode == 0, describe(first)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    again = run(tmp_path, ranks, "--set", "n=80", "--seed", "2", "--out", out)
    assert again.returncode == 2, describe(again)
    lines = [line for line in again.stderr.splitlines() if "error" in line]
    assert len(lines) == 1 and "--restart" in lines[0] and "--overwrite" in lines[0], describe(again)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before  # nothing touched


@pytest.mark.parametrize("ranks", [1, 2, 3])
def test_overwrite_replaces_the_old_run_whole(tmp_path, ranks):
    from mpipack.io.snapshots import list_snapshots, read_snapshot
    out = tmp_path / "A"
    assert run(tmp_path, 1, "--set", "n=50", "--set", "output.snapshot_every=20", "--out", out).returncode == 0
    p = run(tmp_path, ranks, "--set", "n=80", "--seed", "2", "--out", out, "--overwrite")
    assert p.returncode == 0, describe(p)
    s = summary(out)
    assert s["n"] == 80 and s["seed"] == 2 and s["ranks"] == ranks
    fields, _ = read_snapshot(str(out / "snapshots.h5"))
    assert fields["position"].shape[0] == 80
    assert list_snapshots(str(out / "snapshots.h5")) == [0, s["iterations"]]  # no snapshot of the old run


@pytest.mark.parametrize("ranks", [1, 2, 3])
def test_the_default_folder_is_numbered(tmp_path, ranks):
    assert run(tmp_path, 1, "--set", "n=50", "--seed", "1").returncode == 0
    p = run(tmp_path, ranks, "--set", "n=60", "--seed", "2")
    assert p.returncode == 0, describe(p)
    first, second = tmp_path / "mpipack-out" / "default", tmp_path / "mpipack-out" / "default-2"
    assert summary(first)["n"] == 50 and summary(second)["n"] == 60
    assert summary(second)["ranks"] == ranks


def test_restart_continues_in_place_and_overwrite_may_not_remove_its_checkpoint(tmp_path):
    out = tmp_path / "A"
    p = run(tmp_path, 2, "--set", "n=200", "--set", "stop.max_iter=40", "--out", out)
    assert p.returncode == 4 and (out / "checkpoint.h5").exists(), describe(p)
    refused = run(tmp_path, 1, "--restart", out, "--overwrite")
    assert refused.returncode == 2 and "--overwrite" in refused.stderr, describe(refused)
    assert (out / "checkpoint.h5").exists()
    again = run(tmp_path, 3, "--restart", out, "--set", "stop.max_iter=auto")
    assert again.returncode == 0, describe(again)
    assert summary(out)["converged"] and summary(out)["restart_from"]
