#!/usr/bin/env bash
# A single-node Slurm cluster on localhost, for tests and CI: munged, slurmctld and slurmd as
# the current user (root in CI), proctrack/linuxproc, no cgroups, no accounting database.
#
#   pipelines/slurm/local-cluster.sh start DIR   # config, state and logs under DIR; prints
#                                                 # `export SLURM_CONF=DIR/slurm.conf`
#   pipelines/slurm/local-cluster.sh stop DIR
#
# Needs the Debian packages slurm-wlm and munge (.ci/run installs them). Exits non-zero with
# the reason when the cluster does not come up within 60 s. The node offers max(nproc, 4)
# CPUs (slurmd is told to trust the configuration), so that two 2-core stages can share a
# 2-core test machine, as `make -j` would locally.
set -euo pipefail
cmd=${1:?usage: local-cluster.sh start|stop DIR}
dir=$(mkdir -p "${2:?usage: local-cluster.sh start|stop DIR}" && cd "$2" && pwd)

stop() {
  for d in slurmd slurmctld munged; do
    if [ -f "$dir/$d.pid" ]; then
      kill "$(cat "$dir/$d.pid")" 2>/dev/null || true
      rm -f "$dir/$d.pid"
    fi
  done
}

if [ "$cmd" = stop ]; then stop; exit 0; fi
[ "$cmd" = start ] || { echo "local-cluster.sh: unknown command $cmd" >&2; exit 2; }

for exe in munged slurmctld slurmd srun sbatch squeue; do
  command -v "$exe" >/dev/null || [ -x "/usr/sbin/$exe" ] || {
    echo "local-cluster.sh: $exe not found (install the Debian packages slurm-wlm and munge)" >&2
    exit 1
  }
done
export PATH="$PATH:/usr/sbin"
stop
mkdir -p "$dir/state" "$dir/spool" "$dir/log" "$dir/munge"
chmod 700 "$dir/munge"
user=$(id -un)
host=$(hostname -s)
cpus=$(nproc); [ "$cpus" -ge 4 ] || cpus=4
mem_mb=$(awk '/MemTotal/ { print int($2 / 1024 * 0.9) }' /proc/meminfo)

# munge: our own key and socket, so that a system munged (if any) is left alone.
[ -f "$dir/munge/munge.key" ] || {
  dd if=/dev/urandom of="$dir/munge/munge.key" bs=1 count=1024 status=none
  chmod 400 "$dir/munge/munge.key"
}
munged --force --key-file="$dir/munge/munge.key" --socket="$dir/munge/munge.socket" \
  --pid-file="$dir/munged.pid" --log-file="$dir/log/munged.log" --seed-file="$dir/munge/seed"

# The first two free ports from 16817 up (another cluster on this machine keeps its own).
port_free() { ! (exec 3<>"/dev/tcp/127.0.0.1/$1") 2>/dev/null; }
ctld_port=${HBMU_SLURMCTLD_PORT:-16817}
while ! port_free "$ctld_port"; do ctld_port=$((ctld_port + 2)); done
d_port=${HBMU_SLURMD_PORT:-$((ctld_port + 1))}
while ! port_free "$d_port"; do d_port=$((d_port + 2)); done
cat > "$dir/slurm.conf" <<CONF
ClusterName=hbmu-local
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$d_port
SlurmUser=$user
SlurmdUser=$user
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$dir/munge/munge.socket
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SlurmdParameters=config_overrides
ReturnToService=2
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool/%n
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/log/slurmctld.log
SlurmdLogFile=$dir/log/slurmd.log
MpiDefault=none
KillWait=5
InactiveLimit=0
MinJobAge=30
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF="$dir/slurm.conf"
slurmctld -c -f "$SLURM_CONF"
slurmd -f "$SLURM_CONF"

for _ in $(seq 1 60); do
  if sinfo -h -o '%t' 2>/dev/null | grep -qE '^(idle|mix|alloc)'; then
    echo "export SLURM_CONF=$SLURM_CONF"
    exit 0
  fi
  sleep 1
done
echo "local-cluster.sh: the node did not become idle within 60 s; sinfo says:" >&2
sinfo -N -l >&2 || true
tail -n 20 "$dir/log/slurmctld.log" "$dir/log/slurmd.log" >&2 || true
exit 1
