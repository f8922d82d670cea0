#!/usr/bin/env bash
# The quick sweep through SLURM, as emitted: on a single-node SLURM (started with
# tools/slurm-local.sh unless `sinfo` already answers; stopped again if this script started it),
# emit the quick profile's scripts for two seeds with few steps, run `submit.sh` unchanged, wait
# for the jobs, check that every run of every seed is complete and that `calibconv report`
# builds the report. Needs root when it has to start SLURM; .ci/run runs it after `make test`.
#
#   tools/slurm-test.sh            (SLURM_TEST_STEPS=4 SLURM_TEST_TIMEOUT=1200 by default)
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
BIN=$ROOT/target/release/calibconv
STEPS=${SLURM_TEST_STEPS:-4}
# Seconds to wait for the jobs.
TIMEOUT=${SLURM_TEST_TIMEOUT:-1200}
SEEDS=0,1

[ -x "$BIN" ] || { echo "slurm-test: build first (cargo build --release)" >&2; exit 1; }
WORK=$(mktemp -d /tmp/calibconv-slurm-test.XXXXXX)
started=0
jobs=""
cleanup() {
  local rc=$?
  if [ "$rc" != 0 ] && [ -n "$jobs" ]; then
    scancel $jobs 2>/dev/null || true
  fi
  if [ "$started" = 1 ]; then tools/slurm-local.sh stop || true; fi
  if [ "$rc" = 0 ]; then rm -rf "$WORK"; else echo "slurm-test: FAILED; files in $WORK" >&2; fi
}
trap cleanup EXIT

if ! sinfo -h >/dev/null 2>&1; then
  tools/slurm-local.sh start
  started=1
fi
t0=$(date +%s)

# The quick data sets (skipped when complete).
"$BIN" synth --config data/synth-quick.toml >/dev/null

RESULTS=$WORK/results
SWEEP=(sweep experiments/paper --profile quick --seeds "$SEEDS"
       --set "output=$RESULTS" --set "train.steps=$STEPS")
"$BIN" "${SWEEP[@]}" --emit-slurm "$WORK/slurm"
submitted=$(bash "$WORK/slurm/submit.sh")
echo "slurm-test: $submitted"
jobs=$(echo "$submitted" | sed 's/^submitted: *//' | tr ' ' ',')

# Wait until none of the jobs is pending or running.
while [ -n "$(squeue -h -j "$jobs" -o '%i' 2>/dev/null)" ]; do
  if [ $(( $(date +%s) - t0 )) -gt "$TIMEOUT" ]; then
    squeue -j "$jobs" >&2 || true
    echo "slurm-test: the jobs did not finish in $TIMEOUT s" >&2
    exit 1
  fi
  sleep 2
done

# Every run of every seed complete (the sweep's own state check).
plan=$("$BIN" "${SWEEP[@]}" --dry-run 2>&1)
total=$(echo "$plan" | grep -c '^level ' || true)
complete=$(echo "$plan" | grep -c ' Complete' || true)
if [ "$total" = 0 ] || [ "$complete" != "$total" ]; then
  echo "$plan" >&2
  for f in "$WORK"/slurm/slurm-*.out; do echo "== $f" >&2; tail -n 5 "$f" >&2; done
  echo "slurm-test: $complete of $total runs complete" >&2
  exit 1
fi
"$BIN" report "$RESULTS" >/dev/null
[ -f "$RESULTS/REPORT.md" ] || { echo "slurm-test: no REPORT.md" >&2; exit 1; }
echo "slurm-test: ok: $total runs of seeds $SEEDS complete through SLURM ($submitted), report built, in $(( $(date +%s) - t0 )) s"
