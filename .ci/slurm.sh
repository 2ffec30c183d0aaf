#!/usr/bin/env bash
# A single-node Slurm cluster for the batch tests, started and stopped
# without systemd:  .ci/slurm.sh start | stop
# Needs root and Debian's slurmctld, slurmd, slurm-client and munge. The
# configuration, state and logs live in $DEPTHGRAPH_SLURM_STATE
# (default /tmp/depthgraph-slurm); the daemons are stopped by their pid files.
set -euo pipefail
STATE="${DEPTHGRAPH_SLURM_STATE:-/tmp/depthgraph-slurm}"
CONF=/etc/slurm/slurm.conf

stop_pid() {
  local f="$1"
  if [ -s "$f" ]; then
    local pid
    pid="$(cat "$f")"
    if kill -0 "$pid" 2>/dev/null; then
      kill "$pid" 2>/dev/null || true
      for _ in $(seq 1 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
      kill -9 "$pid" 2>/dev/null || true
    fi
    rm -f "$f"
  fi
}

case "${1:-}" in
start)
  host="$(hostname -s)"
  cpus="$(nproc)"
  mem_mb=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 / 2 ))
  mkdir -p "$STATE"/{state,spool,log} /etc/slurm
  # munge: a key, its run directory, the daemon as the munge user
  if [ ! -s /etc/munge/munge.key ]; then
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
  fi
  chown munge:munge /etc/munge/munge.key
  chmod 400 /etc/munge/munge.key
  mkdir -p /run/munge /var/log/munge /var/lib/munge
  chown munge:munge /run/munge /var/log/munge /var/lib/munge
  if ! pgrep -x munged >/dev/null; then
    su -s /bin/sh munge -c "/usr/sbin/munged --pid-file=/run/munge/munged.pid"
    touch "$STATE/started-munged"   # stop only the munged this script started
  fi
  # keep a configuration this script did not write
  if [ -s "$CONF" ] && ! grep -q "written by depthgraph's .ci/slurm.sh" "$CONF"; then
    cp "$CONF" "$STATE/slurm.conf.before"
  fi
  cat >"$CONF" <<CONF
# written by depthgraph's .ci/slurm.sh: one node, root, no cgroups
ClusterName=depthgraph
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/state
SlurmdSpoolDir=$STATE/spool
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/log/slurmctld.log
SlurmdLogFile=$STATE/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SwitchType=switch/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
MaxArraySize=10001
SlurmdTimeout=60
NodeName=$host CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
CONF
  if pgrep -x slurmctld >/dev/null || pgrep -x slurmd >/dev/null; then
    echo "slurm: a slurmctld or slurmd already runs here; not starting a test cluster over it" >&2
    exit 1
  fi
  /usr/sbin/slurmctld -c -f "$CONF"
  /usr/sbin/slurmd -f "$CONF"
  for _ in $(seq 1 120); do
    state="$(sinfo -h -o %t 2>/dev/null | head -1 || true)"
    if [ "$state" = "idle" ]; then
      echo "slurm: node $host idle ($cpus CPUs)"
      exit 0
    fi
    sleep 0.5
  done
  echo "slurm: the node did not become idle; logs:" >&2
  tail -20 "$STATE"/log/*.log >&2 || true
  exit 1
  ;;
stop)
  stop_pid "$STATE/slurmd.pid"
  stop_pid "$STATE/slurmctld.pid"
  if [ -e "$STATE/started-munged" ]; then
    stop_pid /run/munge/munged.pid
    rm -f "$STATE/started-munged"
  fi
  if [ -s "$STATE/slurm.conf.before" ]; then
    mv "$STATE/slurm.conf.before" "$CONF"
  fi
  echo "slurm: stopped"
  ;;
*)
  echo "usage: $0 start|stop" >&2
  exit 2
  ;;
esac
