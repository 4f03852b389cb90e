#!/bin/bash
# shellcheck disable=SC2034  # the settings are read by jobs/lib.sh
# One mpipack run as one Slurm job, in the run folder OUT/<scene>-<job id>. Near the wall time
# (Slurm's SIGUSR1 120 s before the limit, or `mpipack run --walltime` as the backstop) it
# checkpoints and exits 5; submit again with MPIPACK_RUN_DIR to continue it, or use
# jobs/slurm-chain.sh, which does that by itself.
#   sbatch jobs/slurm-run.sh [SCENE] [mpipack run options, e.g. --seed 3 --dump final.npz]
#   continue a run: sbatch --export=ALL,MPIPACK_RUN_DIR=RUN_DIR jobs/slurm-run.sh
# Submit from the mpipack checkout (or set MPIPACK_HOME). Settings: edit below, or give any at
# submission as MPIPACK_<NAME>, e.g. sbatch --export=ALL,MPIPACK_SETS="n=20000" jobs/slurm-run.sh
# ---- settings ------------------------------------------------------------------------------
#SBATCH --job-name=mpipack
#SBATCH --nodes=1
#SBATCH --ntasks=4
#SBATCH --time=01:00:00
#SBATCH --signal=B:USR1@120
#SBATCH --output=mpipack-%j.out
scene=${MPIPACK_SCENE:-default}      # built-in scene (mpipack scenes) or TOML file; or 1st argument
sets=${MPIPACK_SETS:-}               # --set overrides, space-separated: "n=20000 dim=3"
out=${MPIPACK_OUT:-mpipack-out}      # the run folder: OUT/<scene>-<job id>
launcher=${MPIPACK_LAUNCHER:-srun}   # srun (srun --mpi=pmix) or mpirun
margin=${MPIPACK_MARGIN:-60}         # s: mpipack --walltime = the time left at launch - margin
walltime=${MPIPACK_WALLTIME:-}       # or mpipack's --walltime outright, HH:MM:SS
site_env() {                         # puts mpipack and MPI on PATH on the compute node
    # module load openmpi hdf5/openmpi    # e.g.; see jobs/README.md
    . "$MPIPACK_HOME/tools/env.sh"
}
# ---------------------------------------------------------------------------------------------
set -o pipefail  # (no -u: bash 4.2 of older clusters calls an empty array unbound)
cd "${SLURM_SUBMIT_DIR:-.}" || exit 1
MPIPACK_HOME=${MPIPACK_HOME:-$PWD}
# shellcheck source=jobs/lib.sh
. "$MPIPACK_HOME/jobs/lib.sh"
mp_args "$@"
site_env
mp_threads
MP_RANKS=${SLURM_NTASKS:-1}
run_dir=${MPIPACK_RUN_DIR:-$out/$(mp_name "$scene")-$SLURM_JOB_ID}
mp_log "job $SLURM_JOB_ID on $(hostname), $MP_RANKS rank(s)"
mp_warm
mp_backstop "$(mp_seconds "$(squeue -h -j "$SLURM_JOB_ID" -o %L)")"
mp_run "$run_dir" "$walltime"
[ "$MP_CODE" != 5 ] || mp_log "to continue: sbatch --export=ALL,MPIPACK_RUN_DIR=$run_dir jobs/slurm-run.sh"
exit "$MP_CODE"
