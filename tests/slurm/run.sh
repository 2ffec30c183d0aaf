#!/usr/bin/env bash
# The batch as a real Slurm array job (started by .ci/run after
# `.ci/slurm.sh start`): 24 synthetic frames in 6 array tasks of 4, one
# transient failure (frame 9) retried within its task, the manifest
# collected, and every output identical to a local batch of the same frames.
#   tests/slurm/run.sh PATH/TO/depthgraph
set -euo pipefail
cd "$(dirname "$0")/../.."
bin="$(realpath "${1:?usage: tests/slurm/run.sh PATH/TO/depthgraph}")"
work="$(mktemp -d /tmp/depthgraph-slurm-test.XXXXXX)"
trap 'rm -rf "$work"' EXIT
export DEPTHGRAPH_BACKEND=cpu
unset DEPTHGRAPH_FAULT_TRANSIENT
small=(--set scene.width=64 --set scene.height=48 --set refocus.samples=16)

echo "slurm test: local batch"
t0=$(date +%s.%N)
"$bin" batch graphs/sequence_demo.ron --frames 0..24 --out "$work/local" --no-cache --quiet "${small[@]}"
t1=$(date +%s.%N)

echo "slurm test: array job (frame 9 fails once, transiently)"
DEPTHGRAPH_FAULT_TRANSIENT=9 "$bin" batch graphs/sequence_demo.ron --frames 0..24 \
  --out "$work/slurm" --cache-dir "$work/cache" --quiet "${small[@]}" \
  --slurm --frames-per-task 4 --array-max 2 --retries 2 --wait
t2=$(date +%s.%N)

# every frame reported done, frame 9 after a retry, and the outputs are the local batch's
test "$(grep -c '"exit_code":0' "$work/slurm/manifest.jsonl")" -eq 24
grep -q 'retry 1 of 2' "$work"/slurm/slurm/task-*_2.log
test -e "$work/slurm/.fault-transient-9"
(cd "$work/local/frames" && sha256sum ./*.png) >"$work/local.sum"
(cd "$work/slurm/frames" && sha256sum ./*.png) >"$work/slurm.sum"
test "$(wc -l <"$work/local.sum")" -eq 24
diff "$work/local.sum" "$work/slurm.sum"
# collecting again from the parts gives the same manifest
cp "$work/slurm/manifest.jsonl" "$work/first.jsonl"
"$bin" batch --collect "$work/slurm"
diff "$work/first.jsonl" "$work/slurm/manifest.jsonl"
awk -v a="$t0" -v b="$t1" -v c="$t2" 'BEGIN { printf "slurm test: passed (local %.1f s, array job %.1f s with one retry)\n", b - a, c - b }'
