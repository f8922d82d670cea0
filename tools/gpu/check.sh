#!/usr/bin/env bash
# The GPU check, one call on the device machine (<= 8 minutes on an H200): run from the
# repository root with target/gpu/calibconv and target/gpu/cuda-tests carried there (built here
# by tools/gpu/build.sh), e.g. through the device tool:
#   bash tools/gpu/check.sh            (carry: target/gpu/calibconv, target/gpu/cuda-tests)
# Parts, each recorded even when another fails:
#   1. calibconv info (libtorch, CUDA backend, devices, cuDNN)
#   2. the CUDA tests (tests/cuda.rs: op parity against the CPU float64 op, caches per device,
#      a U-Net training step, checkpoints across devices)
#   3. the quick profile end to end on CUDA, one seed (12 runs), then the report
#   4. layers on CUDA, calibrated against cuDNN conv2d: the classic U-Net's at 1088x960 B8 (the
#      paper's) and the study network's (small, depth 3, 144x160 B8)
#   5. the classic U-Net's training step at 1088x960 B8, standard against calibrated, time and
#      peak memory (child processes)
# Writes $OUT/gpu-h200.json (the record's schema, tools/gpu/record.py) and every part's log to
# $OUT (default: target/gpu/check).
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-target/gpu/check}
mkdir -p "$OUT"
BIN=${BIN:-target/gpu/calibconv}
TESTS=${TESTS:-target/gpu/cuda-tests}
PY=${PY:-python3}
# A dry run elsewhere: DEVICE=cpu LAYERS=tiny:32x32:2 STEP=tiny:32x32:2 (every part, small).
DEVICE=${DEVICE:-cuda}
LAYERS=${LAYERS:-classic:1088x960:8 small:144x160:8}
STEP=${STEP:-classic:1088x960:8}
torch_lib=$("$PY" -c 'import os, torch; print(os.path.join(os.path.dirname(torch.__file__), "lib"))')
export LD_LIBRARY_PATH="$torch_lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
start=$(date +%s)
part() { # NAME SECONDS COMMAND...: runs one part with a time limit, logs to $OUT/NAME.log
  local name=$1 limit=$2; shift 2
  local t0=$(date +%s)
  timeout "$limit" "$@" > "$OUT/$name.log" 2>&1
  local rc=$?
  echo "$name: exit $rc in $(( $(date +%s) - t0 )) s" | tee -a "$OUT/parts.txt"
  tail -n 5 "$OUT/$name.log"
}
uptime > "$OUT/load.txt"
part info 30 "$BIN" info --json
cp "$OUT/info.log" "$OUT/info.json"
# (the test that runs the calibconv binary of the build tree is left out: not carried)
part cuda-tests 120 "$TESTS" --test-threads 1 --nocapture --skip cuda_without_cuda_is_refused_before_any_work
part synth 120 "$BIN" synth --config data/synth-quick.toml
sweep_t0=$(date +%s)
part quick 240 "$BIN" sweep experiments/paper --profile quick --seeds 0 --set device=$DEVICE --jobs 1
echo "$(( $(date +%s) - sweep_t0 ))" > "$OUT/quick_wall_s.txt"
part report 60 "$BIN" report results/quick
layer_args=()
for l in $LAYERS; do layer_args+=(--layers "$l"); done
part layers 150 "$BIN" bench-device --device "$DEVICE" --reps 7 "${layer_args[@]}" --json "$OUT/layers.json"
part step 120 "$BIN" bench-device --device "$DEVICE" --reps 5 --step "$STEP" --json "$OUT/step.json"
uptime >> "$OUT/load.txt"
"$PY" tools/gpu/record.py "$OUT" > "$OUT/gpu-h200.json"
echo "gpu check: $(( $(date +%s) - start )) s; record $OUT/gpu-h200.json"
