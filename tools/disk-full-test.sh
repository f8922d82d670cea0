#!/usr/bin/env bash
# A full disk loses nothing. The quick depth baseline (a few steps, a checkpoint after every
# step) trains into a small tmpfs that has room for one checkpoint and a half: the first
# checkpoint is written, the second finds the disk full. The test checks that the run stops with
# an error naming the file and "No space left on device" (exit status 1, not the requeue status
# 75), that the previous checkpoint pair is whole and of one step, that no temporary file is
# left, and that `sweep --status` reports the failure. Then it frees the space, runs the same
# sweep again, and checks that it resumes from that checkpoint, completes, and ends with the
# weights of the same run trained without interruption on the ordinary disk, bit for bit.
#
# Needs root (mount); .ci/run runs it after `make test` (which stays root-free).
#
#   tools/disk-full-test.sh        (DISK_FULL_TEST_STEPS=6 by default)
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=$(pwd)/target/release/calibconv
STEPS=${DISK_FULL_TEST_STEPS:-6}
NAME=paper-depth-bl-pers
# The small file system: room for the run's records and a checkpoint and a half.
SIZE_MB=16

die() { echo "disk-full-test: $*" >&2; exit 1; }
[ "$(id -u)" = 0 ] || die "needs root (mount -t tmpfs)"
[ -x "$BIN" ] || die "build first (cargo build --release)"
WORK=$(mktemp -d /tmp/calibconv-disk-full.XXXXXX)
SMALL=$WORK/small
cleanup() {
  local rc=$?
  if mountpoint -q "$SMALL"; then umount "$SMALL" || true; fi
  if [ "$rc" = 0 ]; then rm -rf "$WORK"; else echo "disk-full-test: FAILED; files in $WORK" >&2; fi
}
trap cleanup EXIT
t0=$(date +%s)

"$BIN" synth --config data/synth-quick.toml >/dev/null
RUN=(sweep experiments/paper --profile quick --seeds 0 --only "$NAME" --threads 1 -q
     --set "train.steps=$STEPS" --set train.checkpoint_every=1 --set "train.val_every=$STEPS")

# The reference, on the ordinary disk; its checkpoint pair gives the size to leave free.
"$BIN" "${RUN[@]}" --set "output=$WORK/reference" >/dev/null 2>&1
REF=$WORK/reference/seed-0/$NAME/checkpoints
pair=$(( $(stat -c %s "$REF/last.safetensors") + $(stat -c %s "$REF/last.optim.safetensors") ))

mkdir -p "$SMALL"
mount -t tmpfs -o "size=${SIZE_MB}m" tmpfs "$SMALL"
free=$(df --output=avail -B1 "$SMALL" | tail -n 1)
leave=$(( pair * 3 / 2 ))
[ "$free" -gt "$leave" ] || die "a ${SIZE_MB} MB tmpfs has $free bytes free, less than $leave"
dd if=/dev/zero of="$SMALL/filler" bs=4096 count=$(( (free - leave) / 4096 )) status=none
echo "disk-full-test: a checkpoint pair is $pair bytes; $(df --output=avail -B1 "$SMALL" | tail -n 1) bytes left free"

SWEEP=("${RUN[@]}" --set "output=$SMALL/results")
CKPT=$SMALL/results/seed-0/$NAME/checkpoints
set +e
"$BIN" "${SWEEP[@]}" > "$WORK/full.log" 2>&1
rc=$?
set -e
cat "$WORK/full.log" | sed 's/^/disk-full-test: full: /'
[ "$rc" = 1 ] || die "the sweep on a full disk exited with $rc, expected 1"
grep -q "cannot write $CKPT/last.*safetensors: No space left on device" "$WORK/full.log" \
  || die "no error naming the checkpoint and the full disk"
# The pair left behind: whole, of one step, before the end; no temporary file.
python3 - "$CKPT" "$STEPS" <<'PY'
import json, struct, sys
def meta(path):
    with open(path, "rb") as f:
        (n,) = struct.unpack("<Q", f.read(8))
        header = json.loads(f.read(n))
        size = max(v["data_offsets"][1] for k, v in header.items() if k != "__metadata__")
        if len(f.read()) != size:
            sys.exit(f"disk-full-test: {path} is truncated")
    return header["__metadata__"]
ckpt, steps = sys.argv[1], int(sys.argv[2])
weights = int(meta(f"{ckpt}/last.safetensors")["step"])
optim = int(meta(f"{ckpt}/last.optim.safetensors")["step"])
if weights != optim or not 1 <= weights < steps:
    sys.exit(f"disk-full-test: the pair left is of steps {weights} and {optim} (of {steps})")
print(f"disk-full-test: the checkpoint pair of step {weights} is whole")
PY
left=$(find "$SMALL/results" -name '.*.tmp-*')
[ -z "$left" ] || die "temporary files left: $left"
status=$("$BIN" "${SWEEP[@]}" --status)
echo "$status" | sed 's/^/disk-full-test: status: /'
echo "$status" | grep -q "failed: .*No space left on device" || die "--status does not show the failure"

# Space freed: the same sweep resumes and completes with the reference's weights.
rm "$SMALL/filler"
"$BIN" "${SWEEP[@]}" > "$WORK/resume.log" 2>&1 || { cat "$WORK/resume.log" >&2; die "the resume failed"; }
"$BIN" "${SWEEP[@]}" --status | grep -q "^seed-0/$NAME .* complete$" || die "not complete after the resume"
python3 tools/same_weights.py "$CKPT" "$REF" | sed 's/^/disk-full-test: /'
echo "disk-full-test: ok: a full disk stopped the run with its last checkpoint whole, and the resume ended with the uninterrupted run's weights, in $(( $(date +%s) - t0 )) s"
