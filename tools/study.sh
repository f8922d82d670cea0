#!/usr/bin/env bash
# The study (issue "The study"): render the data sets, run the paper sweep and the field-of-view
# series with the `study` profile, build the report into docs/study. Every step resumes where it
# stopped (complete runs are skipped), so re-running this script after an interruption continues.
# Wall-clock of each step is appended to results/study/wall.tsv (step, start, end, seconds).
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${STUDY_BIN:-./target/release/calibconv}
JOBS=${STUDY_JOBS:-2}
mkdir -p results/study
step() {
  local name=$1; shift
  local t0; t0=$(date +%s)
  "$@"
  local t1; t1=$(date +%s)
  printf '%s\t%s\t%s\t%s\n' "$name" "$t0" "$t1" "$((t1 - t0))" >> results/study/wall.tsv
}
step synth "$BIN" synth --config data/synth-study.toml
step paper "$BIN" sweep experiments/paper --profile study --jobs "$JOBS" --threads 1
step fov "$BIN" sweep experiments/fov --profile experiments/paper/profiles/study.toml --jobs "$JOBS" --threads 1
step report "$BIN" report results/study --out docs/study
