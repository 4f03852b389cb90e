"""The MPI launcher, seen from its environment: this process's rank and the job's size before
mpi4py is imported (to parse arguments and print on rank 0 only), and the environment a
``mpirun`` started by mpipack itself needs (``mpipack suite``, ``compare``)."""

import os

RANK_VARIABLES = ("OMPI_COMM_WORLD_RANK", "PMIX_RANK", "PMI_RANK", "SLURM_PROCID")
SIZE_VARIABLES = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "SLURM_NTASKS")


def _first_int(names):
    for var in names:
        v = os.environ.get(var)
        if v is not None and v.isdigit():
            return int(v)
    return None


def world_rank():
    """This process's rank under mpirun/srun (0 when not launched by one)."""
    rank = _first_int(RANK_VARIABLES)
    return 0 if rank is None else rank


def world_size():
    """The number of processes mpirun/srun started (1 when not launched by one)."""
    size = _first_int(SIZE_VARIABLES)
    return 1 if size is None else size


def mpi_env():
    """os.environ plus what Open MPI needs to run as root with more ranks than cores (idle ranks
    yield instead of busy-polling), and this checkout first on PYTHONPATH."""
    env = dict(os.environ)
    env["OMPI_ALLOW_RUN_AS_ROOT"] = "1"
    env["OMPI_ALLOW_RUN_AS_ROOT_CONFIRM"] = "1"
    env["OMPI_MCA_rmaps_base_oversubscribe"] = "1"
    env.setdefault("OMPI_MCA_mpi_yield_when_idle", "1")
    env.setdefault("OMPI_MCA_orte_execute_quiet", "1")  # mpipack reads the outcome from summary.json
    env.setdefault("OMPI_MCA_odls_base_sigkill_timeout", "5")  # as tools/env.sh: time to checkpoint
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.pop("PYTHONSTARTUP", None)
    return env
