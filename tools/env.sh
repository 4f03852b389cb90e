# Source me: puts .venv/bin (mpipack, python, pytest) first on PATH and lets Open MPI run as
# root and oversubscribe cores (more ranks than cores), as a laptop or CI user expects.
_mp_top=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
export PATH="$_mp_top/.venv/bin:$PATH"
export VIRTUAL_ENV="$_mp_top/.venv"
if [ "$(id -u)" -eq 0 ]; then
    export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
fi
export OMPI_MCA_rmaps_base_oversubscribe=${OMPI_MCA_rmaps_base_oversubscribe:-1}
unset _mp_top
