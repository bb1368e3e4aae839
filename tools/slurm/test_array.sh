#!/usr/bin/env bash
# Runs a sweep manifest as a Slurm job array on a single-node Slurm started here: munged,
# slurmctld and slurmd in the foreground of this script with a generated config in a temporary
# folder (no system services, any user; root is fine), then stops every daemon it started, on
# success and failure alike. Used by tests/sweep_slurm.rs; needs the Debian packages slurm-wlm and
# munge.
#
#   tools/slurm/test_array.sh MANIFEST RECONSTRUCT_BINARY [TIMEOUT_SECONDS]
#
# Exits 0 when every array task succeeded; prints the task logs either way.
set -euo pipefail
manifest=$(realpath "${1:?manifest}")
bin=$(realpath "${2:?reconstruct binary}")
timeout_s=${3:-150}
here=$(cd "$(dirname "$0")" && pwd)
tasks=$(wc -l < "$manifest")

tmp=$(mktemp -d "${TMPDIR:-/tmp}/reconstruct-slurm.XXXXXX")
chmod 700 "$tmp"
pids=()
job=""
stop() {
    local rc=$?
    if [ -n "$job" ]; then scancel "$job" 2>/dev/null || true; fi
    # Newest first: slurmd, slurmctld, then munged.
    for ((i = ${#pids[@]} - 1; i >= 0; i--)); do
        kill "${pids[i]}" 2>/dev/null || true
        wait "${pids[i]}" 2>/dev/null || true
    done
    if [ "$rc" -ne 0 ]; then
        for log in munged.err slurmctld.log slurmd.log; do
            echo "--- $log" >&2; tail -n 30 "$tmp/$log" >&2 2>/dev/null || true
        done
    fi
    rm -rf "$tmp"
    exit "$rc"
}
trap stop EXIT
trap 'exit 130' INT TERM

# munge: a fresh key and its own socket.
mkdir -m 700 "$tmp/munge"
head -c 1024 /dev/urandom > "$tmp/munge/munge.key"
chmod 400 "$tmp/munge/munge.key"
socket="$tmp/munge/munge.socket"
munged --foreground --force --key-file="$tmp/munge/munge.key" --socket="$socket" \
    --pid-file="$tmp/munge/munged.pid" --log-file="$tmp/munge/munged.log" --seed-file="$tmp/munge/munged.seed" 2> "$tmp/munged.err" &
pids+=($!)
for _ in $(seq 50); do [ -S "$socket" ] && break; sleep 0.1; done
[ -S "$socket" ] || { echo "munged did not start" >&2; cat "$tmp/munge/munged.log" >&2; exit 1; }

# Slurm: this machine as its only node (its real CPUs and memory, from slurmd -C), free ports.
port() { echo $((20000 + RANDOM % 40000)); }
node=$(slurmd -C | head -n 1)
name=$(sed 's/^NodeName=\([^ ]*\).*/\1/' <<< "$node")
mkdir -p "$tmp/state" "$tmp/spool" "$tmp/logs"
export SLURM_CONF="$tmp/slurm.conf"
cat > "$SLURM_CONF" <<CONF
ClusterName=reconstruct-test
SlurmctldHost=$name(127.0.0.1)
SlurmctldPort=$(port)
SlurmdPort=$(port)
SlurmUser=$(id -un)
SlurmdUser=$(id -un)
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$socket
StateSaveLocation=$tmp/state
SlurmdSpoolDir=$tmp/spool
SlurmctldPidFile=$tmp/slurmctld.pid
SlurmdPidFile=$tmp/slurmd.pid
SlurmctldLogFile=$tmp/slurmctld.log
SlurmdLogFile=$tmp/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
ReturnToService=2
MailProg=/bin/true
$node NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
slurmctld -D -i -f "$SLURM_CONF" 2> "$tmp/slurmctld.err" &
pids+=($!)
slurmd -D -f "$SLURM_CONF" 2> "$tmp/slurmd.err" &
pids+=($!)
for _ in $(seq 100); do
    sinfo -h -o %T 2>/dev/null | grep -qxE '(idle|mixed)' && break
    sleep 0.2
done
sinfo -h -o %T | grep -qxE '(idle|mixed)' || { echo "the Slurm node did not come up: $(sinfo 2>&1)" >&2; exit 1; }

# The array: one task per manifest line, 1 CPU and 1 GB each (short runs), logs per task.
export RECONSTRUCT="$bin"
job=$(sbatch --parsable --array=0-$((tasks - 1)) --cpus-per-task=1 --mem=1G --time=00:10:00 \
    --output="$tmp/logs/task-%a.log" "$here/sweep.sbatch" "$manifest")
echo "submitted array job $job with $tasks tasks"
rc=0
deadline=$((SECONDS + timeout_s))
while squeue -h -j "$job" 2>/dev/null | grep -q .; do
    if [ "$SECONDS" -ge "$deadline" ]; then echo "timed out after ${timeout_s} s" >&2; rc=1; break; fi
    sleep 1
done
for log in "$tmp"/logs/task-*.log; do echo "--- $(basename "$log")"; tail -n 15 "$log"; done
# Finished jobs stay in slurmctld's memory for MinJobAge (5 min): their states are the record.
states=$(scontrol -o show job "$job" | grep -o 'JobState=[A-Z_]*' || true)
echo "array job $job:" $(sort <<< "$states" | uniq -c)
completed=$(grep -c '=COMPLETED$' <<< "$states" || true)
[ "$completed" -eq "$tasks" ] || { echo "$completed of $tasks tasks completed" >&2; exit 1; }
exit "$rc"
