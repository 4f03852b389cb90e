"""Helpers of tests/test_jobs.py: a one-node Slurm cluster started by tools/slurm/cluster.sh in a
temporary folder, submission and bounded waits, and fake PBS/LSF commands.

Every wait has a bound: a job that hangs fails its test instead of blocking the suite.
"""

import os
import re
import shutil
import socket
import subprocess
import time
from pathlib import Path

from conftest import SIGKILL_TIMEOUT

REPO = Path(__file__).resolve().parents[1]
JOBS = REPO / "jobs"
CLUSTER_SH = REPO / "tools" / "slurm" / "cluster.sh"
FINAL_STATES = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY",
                "PREEMPTED", "BOOT_FAIL", "DEADLINE"}
# a progress line of mpipack run: iteration, relative change, max overlap, contacts, it/s
PROGRESS = re.compile(r"^\s*(\d+)\s+\d\.\d+e[+-]\d+\s+\d\.\d+e[+-]\d+\s+\d+\s+\d+\s*$", re.M)


def free_port_pair():
    """A port p with p and p + 1 free (slurmctld, slurmd)."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            p = s.getsockname()[1]
        if p >= 65535:
            continue
        try:
            with socket.socket() as s2:
                s2.bind(("127.0.0.1", p + 1))
            return p
        except OSError:
            continue
    return 6817


def slurm_missing():
    """Why a Slurm cluster cannot start here (None if it can be tried)."""
    for cmd in ("slurmctld", "slurmd", "sbatch", "munged", "munge"):
        if shutil.which(cmd) is None:
            return f"{cmd} is not installed (bash tools/slurm/setup.sh installs Slurm and munge)"
    if os.geteuid() != 0:
        return "slurmd (with SlurmdUser=root) must be started as root"
    return None


class Cluster:
    """The daemons of tools/slurm/cluster.sh in ``folder``; job environment and commands."""

    def __init__(self, folder):
        self.folder = Path(folder)
        self.conf = self.folder / "slurm.conf"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith(("MPIPACK_", "SLURM_", "SBATCH_"))}
        self.env.pop(SIGKILL_TIMEOUT, None)  # the jobs' tools/env.sh sets a user's grace
        # the jobs import this checkout's package and find jobs/lib.sh and tools/env.sh here
        self.env.update(SLURM_CONF=str(self.conf), PYTHONPATH=str(REPO), MPIPACK_HOME=str(REPO),
                        SLURM_TEST_PORT=str(free_port_pair()))

    def start(self):
        return subprocess.run(["bash", str(CLUSTER_SH), "start", str(self.folder)], env=self.env,
                              capture_output=True, text=True, timeout=120)

    def stop(self):
        if self.conf.exists():
            subprocess.run(["scancel", "--user=root"], env=self.env, capture_output=True, timeout=30)
        return subprocess.run(["bash", str(CLUSTER_SH), "stop", str(self.folder)], env=self.env,
                              capture_output=True, text=True, timeout=120)

    def logs(self):
        out = []
        for name in ("slurmctld.log", "slurmd.log"):
            p = self.folder / name
            if p.exists():
                out.append(f"--- {name} (tail) ---\n" + "\n".join(p.read_text().splitlines()[-30:]))
        return "\n".join(out)

    def run(self, args, cwd, extra_env=None, timeout=60, stdin=None):
        env = dict(self.env, **(extra_env or {}))
        return subprocess.run([str(a) for a in args], cwd=str(cwd), env=env, capture_output=True,
                              text=True, timeout=timeout, input=stdin)

    def sbatch(self, script, args=(), cwd=".", extra_env=None, options=()):
        p = self.run(["sbatch", "--parsable", *options, script, *args], cwd, extra_env)
        assert p.returncode == 0, f"sbatch failed: {p.stderr}\n{self.logs()}"
        return p.stdout.strip().split(";")[0]

    def job(self, job_id):
        """scontrol's fields of a job (one line, key=value), {} if unknown."""
        p = self.run(["scontrol", "show", "job", "-o", job_id], ".", timeout=30)
        if p.returncode != 0:
            return {}
        return dict(re.findall(r"(\w+)=(\S*)", p.stdout))

    def queue(self):
        p = self.run(["squeue", "-h", "-o", "%i %T"], ".", timeout=30)
        return p.stdout.split("\n") if p.stdout.strip() else []

    def wait_job(self, job_id, timeout):
        """Wait for a job to end; its scontrol fields."""
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            f = self.job(job_id)
            if f.get("JobState") in FINAL_STATES:
                return f
            time.sleep(1)
        raise AssertionError(f"job {job_id} did not end within {timeout} s: {self.job(job_id)}\n"
                             f"queue: {self.queue()}\n{self.logs()}")


def wait_for(predicate, timeout, what, step=0.5):
    """Poll predicate() until it returns a true value (returned); fail after timeout s."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        v = predicate()
        if v:
            return v
        time.sleep(step)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def read(path):
    try:
        return Path(path).read_text()
    except OSError:
        return ""


def last_iteration(text):
    """The iteration of the last progress line in a job's output (0 if none)."""
    its = PROGRESS.findall(text)
    return int(its[-1]) if its else 0


def for_this_machine(script, folder, ntasks=2, time_limit="00:05:00"):
    """A copy of a job script with its settings edited as a user would for a 2-core node."""
    text = Path(script).read_text()
    text = re.sub(r"^#SBATCH --ntasks=\d+$", f"#SBATCH --ntasks={ntasks}", text, flags=re.M)
    text = re.sub(r"^#SBATCH --time=\S+$", f"#SBATCH --time={time_limit}", text, flags=re.M)
    dest = Path(folder) / Path(script).name
    dest.write_text(text)
    dest.chmod(0o755)
    return dest


# ---- fake PBS/LSF: commands that record their arguments ------------------------------------

FAKE_MPIRUN = r"""#!/bin/bash
# fake mpirun: records its arguments and the thread settings; the warm-up (n=200) exits 0; a
# real launch writes summary.json (exit code FAKE_RC) and, unless 0, a checkpoint
echo "mpirun $* | threads $NUMBA_NUM_THREADS $OMP_NUM_THREADS $OPENBLAS_NUM_THREADS" >> "$FAKE_LOG"
case " $* " in *" n=200 --out "*) exit 0 ;; esac
dir=""
args=("$@")
for ((i = 0; i < ${#args[@]}; i++)); do
    case ${args[i]} in --out|--restart) dir=${args[i + 1]} ;; esac
done
mkdir -p "$dir"
code=${FAKE_RC:-0}
printf '{"exit_code": %s, "iterations": 1234, "checkpoint": {"iteration": 1234}}\n' "$code" > "$dir/summary.json"
[ "$code" = 0 ] || [ "$code" = 2 ] || : > "$dir/checkpoint.h5"
exit "$code"
"""
FAKE_QSUB = r"""#!/bin/bash
echo "qsub $*" >> "$FAKE_LOG"
echo "124.pbsserver"
"""
FAKE_BSUB = r"""#!/bin/bash
echo "bsub $*" >> "$FAKE_LOG"
cat > "$FAKE_LOG.stdin"
echo "Job <124> is submitted to queue <normal>."
"""


def fake_bin(folder):
    """A folder holding fake mpirun, qsub and bsub."""
    b = Path(folder) / "fakebin"
    b.mkdir(exist_ok=True)
    for name, text in (("mpirun", FAKE_MPIRUN), ("qsub", FAKE_QSUB), ("bsub", FAKE_BSUB)):
        (b / name).write_text(text)
        (b / name).chmod(0o755)
    return b
