#!/bin/bash
# shellcheck disable=SC2034  # the settings are read by jobs/lib.sh
# A sweep over seeds (or the values of any --set key): a Slurm array job, one task and one run
# folder per value, then a collect job that starts when every task has ended with exit 0
# (--dependency=afterok) and runs `mpipack post compare` over them: SWEEP_DIR/compare.csv,
# compare.json and the overlaid figures compare-*.png.
#   bash jobs/slurm-sweep.sh [SCENE] [mpipack run options]   on the login node: submits both
#   sbatch jobs/slurm-sweep.sh [SCENE] [...]                  the same, from a job of a second
# Run folders: OUT/<scene>-sweep-<array job id>/<key>-<value>. Submit from the mpipack checkout
# (or set MPIPACK_HOME). Settings: edit below, or give any as MPIPACK_<NAME> in the environment.
# ---- settings (the #SBATCH lines are each task's) ------------------------------------------
#SBATCH --job-name=mpipack-sweep
#SBATCH --nodes=1
#SBATCH --ntasks=4
#SBATCH --time=01:00:00
#SBATCH --signal=B:USR1@120
#SBATCH --output=mpipack-%A_%a.out
scene=${MPIPACK_SCENE:-default}      # built-in scene (mpipack scenes) or TOML file; or 1st argument
sets=${MPIPACK_SETS:-}               # --set overrides of every task, space-separated: "n=20000"
key=${MPIPACK_KEY:-seed}             # what the tasks differ in: seed, or a --set key (n, dim, ...)
values=${MPIPACK_VALUES:-1 2 3 4}    # one task per value
out=${MPIPACK_OUT:-mpipack-out}      # the sweep folder: OUT/<scene>-sweep-<array job id>
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
read -ra vals <<< "$values"
name=$(mp_name "$scene")

if [ -n "${MPIPACK_COLLECT:-}" ]; then   # ---- the collect job
    site_env
    mp_threads
    runs=()
    for v in "${vals[@]}"; do runs+=("$MPIPACK_COLLECT/$key-$v"); done
    # one table (compare.csv, compare.json: each run's outcome and its packing's measures, with
    # mean and spread) and overlaid figures (compare-density.png, compare-neighbours.png)
    mpipack post compare "${runs[@]}" --out "$MPIPACK_COLLECT"
    exit $?
fi

if [ -z "${SLURM_ARRAY_TASK_ID:-}" ]; then   # ---- submit the array and the collect job
    shape=()
    [ -z "${SLURM_NTASKS:-}" ] || shape=(--nodes="$SLURM_JOB_NUM_NODES" --ntasks="$SLURM_NTASKS")
    array=$(sbatch --parsable --array="0-$((${#vals[@]} - 1))" "${shape[@]}" \
        --export="ALL,MPIPACK_HOME=$MPIPACK_HOME" "$0" "$@") || exit 1
    array=${array%%;*}
    sweep=$out/$name-sweep-$array
    mkdir -p "$sweep"
    collect=$(sbatch --parsable --dependency="afterok:$array" --nodes=1 --ntasks=1 --time=00:10:00 \
        --job-name=mpipack-collect --output="$sweep/collect-%j.out" \
        --export="ALL,MPIPACK_HOME=$MPIPACK_HOME,MPIPACK_COLLECT=$sweep" "$0" "$@") || exit 1
    echo "sweep of $key over ${vals[*]}: array job $array, collect job ${collect%%;*}; folder $sweep"
    exit 0
fi

# ---- one task of the array
site_env
mp_threads
MP_RANKS=${SLURM_NTASKS:-1}
value=${vals[$SLURM_ARRAY_TASK_ID]}
if [ "$key" = seed ]; then MP_EXTRA+=(--seed "$value"); else MP_SETS+=(--set "$key=$value"); fi
run_dir=$out/$name-sweep-$SLURM_ARRAY_JOB_ID/$key-$value
mp_log "task $SLURM_ARRAY_TASK_ID ($key = $value) of array job $SLURM_ARRAY_JOB_ID on $(hostname), $MP_RANKS rank(s)"
mp_warm
mp_backstop "$(mp_seconds "$(squeue -h -j "$SLURM_JOB_ID" -o %L)")"
mp_run "$run_dir" "$walltime"
exit "$MP_CODE"
