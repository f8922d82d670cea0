#!/usr/bin/env bash
# Builds calibconv for another libtorch than main's: by default torch 2.11 (the device machine's
# torch 2.11.0+cu130) with tch 0.24, the tch release of libtorch 2.11 (main builds tch 0.26
# against torch 2.13). Writes
#   target/gpu/calibconv    the binary (links libtorch_cuda.so: `calibconv info` says so)
#   target/gpu/cuda-tests   the test executable of tests/cuda.rs (the CUDA cases of the suite)
# and touches nothing of main's build: the sources are copied to target/gpu/src with tch's
# version changed in the copy's Cargo.toml, resolved with the second lock file tools/gpu/Cargo.lock
# (updated there when main's dependencies change), built into target/gpu/build. libtorch comes
# from a venv of its own (GPU_VENV, default ~/.cache/calibconv/gpu-venv-torch-$TORCH), created
# from nothing by `pip install torch==$TORCH` (4.6 GB with the CUDA packages) the first time.
#
# On the GPU machine: LD_LIBRARY_PATH="$(python3 -c 'import torch, os;
# print(os.path.dirname(torch.__file__))')/lib" target/gpu/calibconv info
# (tools/gpu/check.sh does this itself).
#
# Environment: TORCH (2.11.0), TCH (0.24), GPU_VENV, PYTHON (python3), JOBS (cargo -j).
set -euo pipefail
cd "$(dirname "$0")/../.."
root=$PWD
TORCH=${TORCH:-2.11.0}
TCH=${TCH:-0.24}
PYTHON=${PYTHON:-python3}
GPU_VENV=${GPU_VENV:-$HOME/.cache/calibconv/gpu-venv-torch-$TORCH}
out=$root/target/gpu
start=$(date +%s)

if [ ! -f "$GPU_VENV/.complete" ]; then
  echo "gpu-build: creating $GPU_VENV (pip install torch==$TORCH, ~4.6 GB)"
  rm -rf "$GPU_VENV"
  mkdir -p "$(dirname "$GPU_VENV")"
  "$PYTHON" -m venv "$GPU_VENV"
  "$GPU_VENV/bin/pip" install --quiet --upgrade pip
  "$GPU_VENV/bin/pip" install --quiet "torch==$TORCH"
  touch "$GPU_VENV/.complete"
fi
libtorch=$("$GPU_VENV/bin/python" -c 'import os, torch; print(os.path.dirname(torch.__file__))')
echo "gpu-build: libtorch $TORCH at $libtorch, tch $TCH"

# The scratch copy: the working tree's sources (uncommitted changes included), not its target.
src=$out/src
mkdir -p "$src/tests"
rm -rf "$src/src" "$src/crates" "$src/data" "$src/tests"
mkdir -p "$src/tests"
cp -r src crates data "$src/"
cp build.rs rustfmt.toml "$src/"
cp tests/*.rs "$src/tests/"
cp -r tests/common "$src/tests/"
# tch's version in the copy; the copy's workspace leaves out the Python package (pyo3).
sed -e "s/^tch = \"[0-9.]*\"/tch = \"$TCH\"/" \
    -e "s/^torch-sys = \"[0-9.]*\"/torch-sys = \"$TCH\"/" \
    -e 's/^members = .*/members = ["crates\/geometry"]/' Cargo.toml > "$src/Cargo.toml"
grep -q "^tch = \"$TCH\"" "$src/Cargo.toml" || { echo "gpu-build: no tch line in Cargo.toml" >&2; exit 1; }
if [ -f tools/gpu/Cargo.lock ]; then cp tools/gpu/Cargo.lock "$src/Cargo.lock"; else cp Cargo.lock "$src/Cargo.lock"; fi

export LIBTORCH=$libtorch LIBTORCH_CXX11_ABI=1 CARGO_TARGET_DIR=$out/build
jobs=()
[ -n "${JOBS:-}" ] && jobs=(-j "$JOBS")
(cd "$src" && cargo build --release "${jobs[@]}" --bin calibconv)
test_exe=$(cd "$src" && cargo test --release "${jobs[@]}" --no-run --test cuda --message-format=json 2>/dev/null \
  | "$GPU_VENV/bin/python" -c 'import json, sys
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and m["target"]["name"] == "cuda" and m.get("executable"):
        print(m["executable"])')
[ -n "$test_exe" ] || { echo "gpu-build: the cuda test executable was not built" >&2; exit 1; }
if ! cmp -s "$src/Cargo.lock" tools/gpu/Cargo.lock 2>/dev/null; then
  cp "$src/Cargo.lock" tools/gpu/Cargo.lock
  echo "gpu-build: tools/gpu/Cargo.lock updated (commit it)"
fi

install -m 755 "$CARGO_TARGET_DIR/release/calibconv" "$out/calibconv"
install -m 755 "$test_exe" "$out/cuda-tests"
strip "$out/calibconv" "$out/cuda-tests"
# The tests read the venv's libtorch folder at CARGO_MANIFEST_DIR/.venv/libtorch; on the device
# they are given LD_LIBRARY_PATH instead, and never look there.
size=$(du -cb "$out/calibconv" "$out/cuda-tests" | tail -1 | cut -f1)
readelf -d "$out/calibconv" | grep -q 'NEEDED.*libtorch_cuda.so' \
  || { echo "gpu-build: target/gpu/calibconv does not link libtorch_cuda.so" >&2; exit 1; }
limit=$((48 * 1024 * 1024))
[ "$size" -le "$limit" ] || { echo "gpu-build: $size bytes > 48 MiB" >&2; exit 1; }
LD_LIBRARY_PATH="$libtorch/lib" "$out/calibconv" info
echo "gpu-build: target/gpu/calibconv and target/gpu/cuda-tests, $((size / 1024 / 1024)) MiB together, in $(( $(date +%s) - start )) s"
