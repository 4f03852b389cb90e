# Source me: puts .venv/bin (mpipack, python, pytest) first on PATH and lets Open MPI run as
# root and oversubscribe cores (more ranks than cores), as a laptop or CI user expects.
_mp_top=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export PATH="$_mp_top/.venv/bin:$PATH"
export VIRTUAL_ENV="$_mp_top/.venv"
if [ "$(id -u)" -eq 0 ]; then
    export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
fi
export OMPI_MCA_rmaps_base_oversubscribe=${OMPI_MCA_rmaps_base_oversubscribe:-1}
# more ranks than cores (an empty rank, a 2-core laptop): give the core away while waiting in
# MPI instead of busy-polling (N = 3 on 2 ranks: 35.7 s of loop without it, 10.6 s with it)
export OMPI_MCA_mpi_yield_when_idle=${OMPI_MCA_mpi_yield_when_idle:-1}
# a clean error exit (mpipack prints one line and every rank exits with the same code) is not
# followed by Open MPI's ten-line "job has been aborted" notice; the exit code is kept
export OMPI_MCA_orte_execute_quiet=${OMPI_MCA_orte_execute_quiet:-1}
unset _mp_top
