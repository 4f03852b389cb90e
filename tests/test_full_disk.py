"""A full disk (ENOSPC) hung every multi-rank run: one rank failed inside a collective HDF5
call while the others waited in it. The writers now look at the room left before any
collective call and agree on the verdict; the run stops with one line (exit 2), its summary,
and the previous checkpoint whole. Each test mounts a small tmpfs (root; skipped where it
cannot)."""

import json
import subprocess
import sys

import numpy as np
import pytest

from conftest import describe, mpirun

pytestmark = pytest.mark.mpi


@pytest.fixture
def small_disk(tmp_path, request):
    """A tmpfs of 512 KiB (or the size a test's ``disk_size`` mark gives) at tmp_path/disk."""
    mark = request.node.get_closest_marker("disk_size")
    size = mark.args[0] if mark else "512k"
    mnt = tmp_path / "disk"
    mnt.mkdir()
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if p.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {p.stderr.strip()}")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def run_into(tmp_path, ranks, out, sets):
    args = [sys.executable, "-m", "mpipack.cli", "run", "--quiet", "--out", str(out)]
    for s in sets:
        args += ["--set", s]
    return mpirun(ranks, args, tmp_path, timeout=300)


@pytest.mark.parametrize("ranks", [1, 2, 3])
@pytest.mark.parametrize("what,sets", [
    ("snapshot", ["n=3000", "output.snapshot_every=20", "stop.max_iter=200"]),
    ("checkpoint", ["n=3000", "output.snapshots=false", "output.checkpoint_every=20", "stop.max_iter=200"]),
    ("final snapshot", ["n=3000", "stop.max_iter=30"]),
])
def test_a_full_disk_stops_the_run_in_one_line(tmp_path, small_disk, ranks, what, sets):
    out = small_disk / "run"
    p = run_into(tmp_path, ranks, out, sets)
    assert p.returncode == 2, describe(p)
    errors = [line for line in p.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "no room" in errors[0] and "Traceback" not in p.stderr, describe(p)
    s = json.loads((out / "summary.json").read_text())
    assert s["exit_code"] == 2 and "no room" in s["output_failed"], s
    assert not [f for f in out.iterdir() if f.name.endswith(".tmp")]  # no temporary file left
    if what == "final snapshot":  # the start's snapshot (iteration 0) was the first refused: the run
        # stopped after its first iteration, and its figures are in the summary
        assert s["iterations"] == 1 and s["W"] > 0


@pytest.mark.disk_size("3m")
def test_the_previous_checkpoint_stays_whole_when_the_disk_fills(tmp_path, small_disk):
    from mpipack.io.checkpoint import CheckpointError, read_checkpoint, write_checkpoint
    from mpipack.parallel.comm import Comm
    comm, n = Comm(), 1000
    rng = np.random.default_rng(0)
    block = {"gid_lo": 0, "x": rng.normal(size=(n, 2)), "x_prev": rng.normal(size=(n, 2)),
             "diam": np.ones(n), "hist_count": np.zeros(n, np.int64), "hist_gid": np.zeros(0, np.int64),
             "hist_lambda": np.zeros(0)}
    path = small_disk / "checkpoint.h5"
    write_checkpoint(comm, path, n, 2, block, {"iteration": 1}, {})
    (small_disk / "filler").write_bytes(b"\0" * (2 * 1024 * 1024))  # 3 MiB - 2 MiB: less than 1.1 MiB left
    with pytest.raises(CheckpointError, match="no room"):
        write_checkpoint(comm, path, n, 2, {**block, "x": block["x"] + 1.0}, {"iteration": 2}, {})
    got, scalars, _ = read_checkpoint(comm, path)
    assert scalars["iteration"] == 1 and np.array_equal(got["x"], block["x"])
    assert [f.name for f in small_disk.iterdir() if f.name.endswith(".tmp")] == []


@pytest.mark.parametrize("ranks", [1, 2, 3])
def test_a_metrics_file_that_cannot_grow_stops_every_rank(tmp_path, small_disk, ranks):
    """metrics.csv is rank 0's alone: its failure is broadcast, so that every rank stops (rank 0
    leaving the loop alone left the others waiting in the next reduction)."""
    out = small_disk / "run"
    out.mkdir()
    try:  # the disk full to the last byte
        with open(small_disk / "filler", "wb", buffering=0) as f:
            while True:
                f.write(b"\0" * 4096)
    except OSError:
        pass
    p = run_into(tmp_path, ranks, out, ["n=200", "output.metrics_every=5", "output.snapshots=false",
                                       "stop.rule=eps", "stop.eps=0", "stop.max_iter=100"])
    assert p.returncode == 2, describe(p)
    errors = [line for line in p.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "metrics.csv" in errors[0], describe(p)
