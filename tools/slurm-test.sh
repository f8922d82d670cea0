#!/usr/bin/env bash
# The quick sweep through SLURM, as emitted: on a single-node SLURM (started with
# tools/slurm-local.sh unless `sinfo` already answers; stopped again if this script started it),
# emit the quick profile's scripts for two seeds with few steps, run `submit.sh` unchanged, wait
# for the jobs, check that every run of every seed is complete and that `calibconv report`
# builds the report.
#
# Then a run longer than its time limit: the quick depth baseline with SLURM_TEST_REQUEUE_STEPS
# steps (about two minutes of training here) under a one-minute limit, SIGUSR1 asked for
# SLURM_TEST_SIGNAL seconds before it. The emitted scripts run unchanged; each time the task is
# warned, calibconv writes its checkpoint and exits with status 75, the script requeues the
# task, and it resumes. The test checks that it completes, that it was requeued at least once
# (run.json's segments), that `--status` calls it complete, and that its final and best weights
# equal, bit for bit, those of the same run trained here without interruption (at the same time,
# one thread each). It does not depend on how fast the machine is, as long as the training
# outlasts one limit: a slower machine only adds requeues.
#
# Needs root when it has to start SLURM; .ci/run runs it after `make test`.
#
#   tools/slurm-test.sh   (SLURM_TEST_STEPS=4 SLURM_TEST_REQUEUE_STEPS=1500 SLURM_TEST_SIGNAL=15
#                          SLURM_TEST_TIMEOUT=1200 by default)
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
BIN=$ROOT/target/release/calibconv
STEPS=${SLURM_TEST_STEPS:-4}
REQUEUE_STEPS=${SLURM_TEST_REQUEUE_STEPS:-1500}
SIGNAL=${SLURM_TEST_SIGNAL:-15}
REQUEUE_RUN=paper-depth-bl-pers
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
# Submits OUT/submit.sh as written; prints the job ids, comma-separated.
submit() {
  local out
  out=$(bash "$1/submit.sh")
  echo "$out" | sed 's/^/slurm-test: /' >&2
  echo "$out" | sed -n 's/^submitted: *//p' | tr ' ' ','
}

# Waits until none of the jobs $1 is pending or running; with a second argument (a status
# command) prints the sweep's status every 30 s while it waits.
wait_jobs() {
  local last=0
  while [ -n "$(squeue -h -j "$1" -o '%i' 2>/dev/null)" ]; do
    if [ $(( $(date +%s) - t0 )) -gt "$TIMEOUT" ]; then
      squeue -j "$1" >&2 || true
      echo "slurm-test: the jobs did not finish in $TIMEOUT s" >&2
      exit 1
    fi
    if [ $# -gt 1 ] && [ $(( $(date +%s) - last )) -ge 30 ]; then
      "${@:2}" | sed 's/^/slurm-test: status: /' || true
      last=$(date +%s)
    fi
    sleep 2
  done
}

jobs=$(submit "$WORK/slurm")
wait_jobs "$jobs"

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
echo "slurm-test: ok: $total runs of seeds $SEEDS complete through SLURM (jobs $jobs), report built, in $(( $(date +%s) - t0 )) s"

# A run longer than its time limit, through requeues.
t1=$(date +%s)
LONG=(sweep experiments/paper --profile quick --seeds 0 --only "$REQUEUE_RUN"
      --set "train.steps=$REQUEUE_STEPS")
"$BIN" "${LONG[@]}" --set "output=$WORK/requeue" --emit-slurm "$WORK/slurm-requeue" \
  --slurm-set time=00:01:00 --slurm-set "signal_seconds=$SIGNAL" >/dev/null
jobs=$(submit "$WORK/slurm-requeue")
# The same run without interruption, here, meanwhile (one thread, as the task's one CPU).
"$BIN" "${LONG[@]}" --set "output=$WORK/reference" --threads 1 -q > "$WORK/reference.log" 2>&1 &
reference=$!
wait_jobs "$jobs" "$BIN" "${LONG[@]}" --set "output=$WORK/requeue" --status
wait "$reference" || { cat "$WORK/reference.log" >&2; echo "slurm-test: the reference run failed" >&2; exit 1; }
status=$("$BIN" "${LONG[@]}" --set "output=$WORK/requeue" --status)
echo "$status" | sed 's/^/slurm-test: status: /'
RUN=$WORK/requeue/seed-0/$REQUEUE_RUN
if ! echo "$status" | grep -q "^seed-0/$REQUEUE_RUN .* complete$"; then
  for f in "$WORK"/slurm-requeue/slurm-*.out; do echo "== $f" >&2; tail -n 20 "$f" >&2; done
  echo "slurm-test: the run with a one-minute limit did not complete" >&2
  exit 1
fi
# Segments of run.json: how many times it stopped on the warning and was requeued.
python3 - "$RUN/run.json" > "$WORK/segments.txt" <<'PY'
import json, sys
segments = json.load(open(sys.argv[1]))["segments"]
for s in segments:
    print("segment: steps %s-%s on %s, SLURM job %s, restart %s: %s" % (s["first_step"],
          s["last_step"], s["host"], s.get("slurm_job"), s.get("slurm_restarts"), s["reason"]))
print("requeues", sum(s["reason"] == "interrupted" for s in segments))
PY
sed 's/^/slurm-test: /' "$WORK/segments.txt"
requeues=$(sed -n 's/^requeues //p' "$WORK/segments.txt")
if [ "$requeues" -lt 1 ]; then
  echo "slurm-test: the run finished within one limit, so nothing was tested: raise SLURM_TEST_REQUEUE_STEPS" >&2
  exit 1
fi
# Final and best weights, bit for bit (tensors only: see tools/same_weights.py).
python3 tools/same_weights.py "$RUN/checkpoints" "$WORK/reference/seed-0/$REQUEUE_RUN/checkpoints" \
  | sed 's/^/slurm-test: /'
echo "slurm-test: ok: $REQUEUE_RUN ($REQUEUE_STEPS steps, limit 1 min) completed through $requeues requeue(s) (jobs $jobs) with the uninterrupted run's weights, in $(( $(date +%s) - t1 )) s"
echo "slurm-test: all in $(( $(date +%s) - t0 )) s"
