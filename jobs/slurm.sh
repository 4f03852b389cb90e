#!/bin/bash
# Run a scene on a Slurm cluster:  sbatch jobs/slurm.sh [scene] [--set key=value ...]
# Set up once beforehand, from the repository root: bash tools/setup.sh
# (srun needs Slurm's PMIx plugin for Open MPI; where it is missing use: mpirun mpipack run ...)
#
# Running out of time is not losing the run: Slurm sends SIGUSR1 two minutes before the limit
# (--signal), every rank checkpoints at the same iteration and mpipack exits with code 5. The
# script then resubmits itself; the next job continues from the checkpoint (--restart), on
# any number of ranks, bit for bit as if it had never stopped.
#SBATCH --job-name=mpipack
#SBATCH --ntasks=4
#SBATCH --time=01:00:00
#SBATCH --signal=USR1@120
#SBATCH --output=mpipack-%j.log
set -uo pipefail
cd "${SLURM_SUBMIT_DIR:-.}"
. tools/env.sh
scene=${1:-default}
shift || true
out="mpipack-out/$(basename "$scene" .toml)-${MPIPACK_RUN_ID:-${SLURM_JOB_ID:-local}}"
if [ -f "$out/checkpoint.h5" ]; then
    srun mpipack run --restart "$out" "$@"
else
    srun mpipack run "$scene" --out "$out" "$@"
fi
rc=$?
if [ "$rc" -eq 5 ] && [ -n "${SLURM_JOB_ID:-}" ]; then
    # stopped with a checkpoint: continue in a new job, in the same run folder
    sbatch --export=ALL,MPIPACK_RUN_ID="${MPIPACK_RUN_ID:-$SLURM_JOB_ID}" "$0" "$scene" "$@"
fi
exit "$rc"
