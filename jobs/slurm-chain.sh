#!/bin/bash
# shellcheck disable=SC2034  # the settings are read by jobs/lib.sh
# A long run as a chain of Slurm jobs. Each link runs until shortly before its wall time (Slurm's
# SIGUSR1 120 s before the limit, forwarded to mpipack; `mpipack run --walltime` as the backstop,
# because the signal can come late), checkpoints and submits the next link, which continues from
# the checkpoint bit for bit -- until the run is certified, stops for a reason a new link would
# not cure (exit 2, 3, 4), is cancelled, or max_links is reached. RUN_DIR/chain.log tells the
# story across links.
#   sbatch jobs/slurm-chain.sh [SCENE] [mpipack run options, e.g. --seed 3 --dump final.npz]
#   continue a stopped chain: sbatch --export=ALL,MPIPACK_RUN_DIR=RUN_DIR jobs/slurm-chain.sh
# Submit from the mpipack checkout (or set MPIPACK_HOME). Settings: edit below, or give any at
# submission as MPIPACK_<NAME>, e.g. sbatch --export=ALL,MPIPACK_SETS="n=20000" jobs/slurm-chain.sh
# ---- settings ------------------------------------------------------------------------------
#SBATCH --job-name=mpipack-chain
#SBATCH --nodes=1
#SBATCH --ntasks=4
#SBATCH --time=01:00:00
#SBATCH --signal=B:USR1@120
#SBATCH --output=mpipack-%j.out
scene=${MPIPACK_SCENE:-default}      # built-in scene (mpipack scenes) or TOML file; or 1st argument
sets=${MPIPACK_SETS:-}               # --set overrides, space-separated: "n=20000 dim=3"
out=${MPIPACK_OUT:-mpipack-out}      # the run folder: OUT/<scene>-<first job id>
launcher=${MPIPACK_LAUNCHER:-srun}   # srun (srun --mpi=pmix) or mpirun
max_links=${MPIPACK_MAX_LINKS:-10}   # the most jobs one run may take
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
link=${MPIPACK_LINK:-1}
run_dir=${MPIPACK_RUN_DIR:-$out/$(mp_name "$scene")-$SLURM_JOB_ID}
mkdir -p "$run_dir"
MP_LOG=$run_dir/chain.log
mp_log "link $link of at most $max_links: job $SLURM_JOB_ID on $(hostname), $MP_RANKS rank(s)"
mp_warm
mp_backstop "$(mp_seconds "$(squeue -h -j "$SLURM_JOB_ID" -o %L)")"
mp_run "$run_dir" "$walltime"
mp_decide "$link" "$max_links" "$run_dir"
if [ "$MP_NEXT" = 1 ]; then
    # the next link: this script, its arguments, and this job's shape (as submitted, e.g. -n 64)
    shape=(--job-name="$SLURM_JOB_NAME" --nodes="$SLURM_JOB_NUM_NODES" --ntasks="$MP_RANKS")
    limit=$(squeue -h -j "$SLURM_JOB_ID" -o %l)
    [ -z "$(mp_seconds "$limit")" ] || shape+=(--time="$limit")
    [ -z "${SLURM_JOB_PARTITION:-}" ] || shape+=(--partition="$SLURM_JOB_PARTITION")
    if next=$(sbatch --parsable --dependency="afterany:$SLURM_JOB_ID" "${shape[@]}" \
            --export="ALL,MPIPACK_RUN_DIR=$run_dir,MPIPACK_LINK=$((link + 1)),MPIPACK_HOME=$MPIPACK_HOME" "$0" "$@"); then
        mp_log "link $((link + 1)) submitted: job ${next%%;*}"
        exit 0
    fi
    mp_log "chain ends: sbatch failed; to continue, submit again with MPIPACK_RUN_DIR=$run_dir"
fi
exit "$MP_CODE"
