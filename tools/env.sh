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
# SIGTERM or SIGINT to mpirun (a scheduler, timeout, Ctrl-C): mpirun forwards it to the ranks
# after this many seconds and kills them as many seconds later. Open MPI's default, 1 s, is too
# short for a large run to checkpoint (2D N = 1e6 on 2 ranks: 0.93 s from the signal to its
# summary, docs/benchmarks.md); 5 s leaves room. Open MPI's notices (a rank killed by a signal,
# by the OOM killer) are not hidden.
export OMPI_MCA_odls_base_sigkill_timeout=${OMPI_MCA_odls_base_sigkill_timeout:-5}
unset _mp_top
