#!/usr/bin/env bash
# A single-node SLURM on this machine, for tools/slurm-test.sh (Debian `slurm-wlm`: munge,
# slurmctld, slurmd; no accounting database, no cgroups).
#
#   tools/slurm-local.sh start    apt-get update + install (if missing), write the config, start
#                                 munged, slurmctld and slurmd, wait until the node is idle
#   tools/slurm-local.sh stop     stop the three daemons by the PIDs they wrote
#   tools/slurm-local.sh status   sinfo
#
# Needs root. Everything it writes is under $SLURM_LOCAL_DIR (default /var/tmp/calibconv-slurm:
# config, PID files, logs, spool) plus /etc/slurm/slurm.conf, a link to its config (an
# /etc/slurm/slurm.conf that this script did not write is left alone: then it stops). The node
# is this machine as `slurmd -C` sees it (CPUs, memory), in partition `local`.
set -euo pipefail

STATE=${SLURM_LOCAL_DIR:-/var/tmp/calibconv-slurm}
CONF=/etc/slurm/slurm.conf
MARK="# written by calibconv tools/slurm-local.sh"
# How long to wait for the node to come up, in seconds.
UP_TIMEOUT=60

die() { echo "slurm-local: $*" >&2; exit 1; }

[ "$(id -u)" = 0 ] || die "needs root (apt-get, daemons)"

install() {
  if command -v slurmctld >/dev/null && command -v slurmd >/dev/null && command -v munged >/dev/null; then
    return
  fi
  echo "slurm-local: installing slurm-wlm and munge (apt-get)"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -q
  apt-get install -y -q --no-install-recommends slurm-wlm munge
}

write_config() {
  mkdir -p "$STATE"/ctld "$STATE"/d /etc/slurm
  if [ -e "$CONF" ] && ! grep -qF "$MARK" "$CONF"; then
    die "$CONF exists and was not written by this script; not touching it"
  fi
  local host node
  host=$(hostname -s)
  # The node as slurmd detects it (CPUs, sockets, cores, threads, RealMemory).
  node=$(slurmd -C | head -n 1)
  case "$node" in
    NodeName=*) ;;
    *) die "slurmd -C printed no node line: $node" ;;
  esac
  cat > "$STATE/slurm.conf" <<EOF
$MARK: a single-node cluster on $host.
ClusterName=calibconv-local
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$STATE/ctld
SlurmdSpoolDir=$STATE/d
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$STATE/slurmctld.log
SlurmdLogFile=$STATE/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
SlurmdTimeout=300
# A requeued job waits cred_expire seconds (default 120) before it may start again, then for the
# scheduler's next pass (default every 30-60 s): short here, so that tools/slurm-test.sh's
# requeued task restarts in seconds, not minutes.
AuthInfo=cred_expire=10
SchedulerParameters=sched_interval=5,bf_interval=5
$node NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=local Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
  ln -sfn "$STATE/slurm.conf" "$CONF"
}

running() { [ -f "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

start() {
  install
  write_config
  # munge: its key comes with the package; make one if it is missing.
  if [ ! -s /etc/munge/munge.key ]; then
    mungekey --create --keyfile=/etc/munge/munge.key 2>/dev/null \
      || dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
  fi
  chown munge:munge /etc/munge/munge.key && chmod 400 /etc/munge/munge.key
  mkdir -p /run/munge /var/log/munge /var/lib/munge
  chown munge:munge /run/munge /var/log/munge /var/lib/munge
  if ! running /run/munge/munged.pid; then
    runuser -u munge -- /usr/sbin/munged
    touch "$STATE/started-munged"
  fi
  munge -n | unmunge >/dev/null || die "munge does not work (see /var/log/munge/munged.log)"
  running "$STATE/slurmctld.pid" || slurmctld
  running "$STATE/slurmd.pid" || slurmd
  local t=0
  until sinfo -h -o '%T' 2>/dev/null | grep -qE '^(idle|mixed|allocated)'; do
    t=$((t + 1))
    if [ "$t" -gt "$UP_TIMEOUT" ]; then
      sinfo >&2 || true
      tail -n 20 "$STATE/slurmctld.log" "$STATE/slurmd.log" >&2 || true
      die "the node did not come up in $UP_TIMEOUT s"
    fi
    sleep 1
  done
  echo "slurm-local: up ($(sinfo -h -o '%P %D node(s) %c CPUs %T'))"
}

stop_pid() {
  local file=$1 name=$2
  if running "$file"; then
    local pid
    pid=$(cat "$file")
    kill "$pid"
    for _ in $(seq 1 30); do
      kill -0 "$pid" 2>/dev/null || break
      sleep 0.5
    done
    if kill -0 "$pid" 2>/dev/null; then
      echo "slurm-local: $name ($pid) did not stop; killing it" >&2
      kill -9 "$pid" || true
    fi
    echo "slurm-local: stopped $name ($pid)"
  fi
}

stop() {
  stop_pid "$STATE/slurmd.pid" slurmd
  stop_pid "$STATE/slurmctld.pid" slurmctld
  # munged only if this script started it (another service may use it).
  if [ -f "$STATE/started-munged" ]; then
    stop_pid /run/munge/munged.pid munged
    rm -f "$STATE/started-munged"
  fi
}

case "${1:-}" in
  start) start ;;
  stop) stop ;;
  status) sinfo ;;
  *) echo "usage: $0 start|stop|status" >&2; exit 2 ;;
esac
