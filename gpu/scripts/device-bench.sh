#!/usr/bin/env bash
# The GPU bench on a real GPU machine that has no network.
#
#   gpu/scripts/device-bench.sh prepare   # here: build the bench, fetch the Vulkan loader
#   gpu/scripts/device-bench.sh run [OUT] # there, from the repository root: run it
#
# `prepare` leaves two ignored folders in the repository root: .gpu-bench
# (the bench binary) and .gl (Debian packages of the Vulkan loader and GL
# dispatch libraries, amd64). Carry both to the machine with the working
# tree (graphs/ must be there too) and call `run` there in one command; it
# unpacks the loader, points it at the NVIDIA driver's ICD when one is
# installed, runs CPU and GPU on the same inputs (1600x1200 at 576 samples
# included), and writes the table to OUT/bench.md (default: stdout only).
set -euo pipefail
cd "$(dirname "$0")/../.."

case "${1:-}" in
prepare)
  for d in .gpu-bench .gl; do
    grep -qx "/$d/" .git/info/exclude 2>/dev/null || { mkdir -p .git/info; echo "/$d/" >>.git/info/exclude; }
  done
  exe=$(cargo bench -p depthgraph-gpu --bench gpu --no-run --message-format=json 2>/dev/null |
    sed -n 's/.*"executable":"\([^"]*\)".*/\1/p' | tail -1)
  [ -x "$exe" ] || { echo "device-bench: the bench did not build" >&2; exit 1; }
  mkdir -p .gpu-bench
  cp "$exe" .gpu-bench/gpu-bench
  if ! ls .gl/*.deb >/dev/null 2>&1; then
    mkdir -p .gl /tmp/amd64/partial
    o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
    # shellcheck disable=SC2086
    apt-get $o update >/dev/null
    # shellcheck disable=SC2086
    (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
  fi
  du -sh .gpu-bench .gl
  echo "carry: .gpu-bench .gl; then run: gpu/scripts/device-bench.sh run \$OUT"
  ;;
run)
  out="${2:-}"
  if ls .gl/*.deb >/dev/null 2>&1; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
  fi
  icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
  if [ -f "$icd" ] && [ -z "${VK_DRIVER_FILES:-}" ]; then
    export VK_DRIVER_FILES=$icd
  fi
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader || true
  export DEPTHGRAPH_ROOT="$PWD" DEPTHGRAPH_BENCH_FULL=1 RAYON_NUM_THREADS="${RAYON_NUM_THREADS:-$(nproc)}"
  if [ -n "$out" ]; then
    mkdir -p "$out"
    .gpu-bench/gpu-bench | tee "$out/bench.md"
  else
    .gpu-bench/gpu-bench
  fi
  ;;
*)
  echo "usage: $0 prepare | run [OUT]" >&2
  exit 2
  ;;
esac
