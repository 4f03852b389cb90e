#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, all of its state in one folder (for the job-script
# tests; run as root after tools/slurm/setup.sh):
#   tools/slurm/cluster.sh start DIR   write DIR/slurm.conf, start munged (unless one answers),
#                                      slurmctld and slurmd; wait until the node is idle
#   tools/slurm/cluster.sh stop DIR    stop the daemons started by "start DIR", by their pid files
# Then: export SLURM_CONF=DIR/slurm.conf; sbatch ... . Ports: SLURM_TEST_PORT (default 6817)
# for slurmctld and the next one for slurmd.
set -euo pipefail
cmd=${1:?usage: cluster.sh start|stop DIR}
dir=$(mkdir -p "${2:?usage: cluster.sh start|stop DIR}" && cd "$2" && pwd)
conf=$dir/slurm.conf
export SLURM_CONF=$conf
say() { printf '[slurm] %s\n' "$*"; }

stop_pid() {  # stop_pid NAME: TERM the daemon of DIR/NAME.pid, KILL it after 10 s
    local f=$dir/$1.pid pid
    [ -s "$f" ] || return 0
    pid=$(cat "$f")
    if kill -0 "$pid" 2>/dev/null; then
        kill "$pid" 2>/dev/null || true
        for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
        if kill -0 "$pid" 2>/dev/null; then kill -9 "$pid" 2>/dev/null || true; fi
        say "stopped $1 (pid $pid)"
    fi
    rm -f "$f"
}

if [ "$cmd" = stop ]; then
    stop_pid slurmd; stop_pid slurmctld; stop_pid munged
    exit 0
fi
[ "$cmd" = start ] || { echo "usage: cluster.sh start|stop DIR" >&2; exit 2; }
[ "$(id -u)" -eq 0 ] || { echo "cluster.sh: must run as root (slurmd)" >&2; exit 1; }
command -v slurmctld >/dev/null || { echo "cluster.sh: slurmctld not installed (run tools/slurm/setup.sh)" >&2; exit 1; }

# ---- munge: Slurm's authentication; reuse a running munged, else start one (stopped by "stop")
mkdir -p "$dir/spool" "$dir/state"
if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    if [ ! -s /etc/munge/munge.key ]; then
        dd if=/dev/urandom bs=1 count=1024 of=/etc/munge/munge.key status=none
        chown munge:munge /etc/munge/munge.key; chmod 400 /etc/munge/munge.key
    fi
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge:munge /run/munge /var/log/munge /var/lib/munge
    rm -f /run/munge/munged.pid
    # munged's own files where the package puts them (user munge cannot enter a private /tmp folder)
    runuser -u munge -- /usr/sbin/munged
    for _ in $(seq 50); do [ -s /run/munge/munged.pid ] && break; sleep 0.1; done
    cp /run/munge/munged.pid "$dir/munged.pid"
    munge -n | unmunge >/dev/null || { echo "cluster.sh: munged does not answer" >&2; exit 1; }
    say "started munged (pid $(cat "$dir/munged.pid"))"
fi

port=${SLURM_TEST_PORT:-6817}
cpus=$(nproc)
cat > "$conf" <<CONF
ClusterName=mpipacktest
SlurmctldHost=localhost
SlurmctldPort=$port
SlurmdPort=$((port + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
MpiDefault=none
ReturnToService=2
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
MailProg=/bin/true
SchedulerParameters=sched_interval=2
KillWait=30
MinJobAge=600
NodeName=localhost CPUs=$cpus State=UNKNOWN
PartitionName=debug Nodes=localhost Default=YES MaxTime=INFINITE State=UP
CONF
slurmctld -f "$conf"   # forks; writes its pid file
slurmd -f "$conf"
for _ in $(seq 60); do
    if sinfo -h -o %t 2>/dev/null | grep -qx idle; then
        say "node idle: slurmctld pid $(cat "$dir/slurmctld.pid"), slurmd pid $(cat "$dir/slurmd.pid"); export SLURM_CONF=$conf"
        exit 0
    fi
    sleep 0.5
done
echo "cluster.sh: the node did not become idle in 30 s; see $dir/slurmctld.log and $dir/slurmd.log" >&2
exit 1
