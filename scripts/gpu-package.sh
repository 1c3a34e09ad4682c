#!/usr/bin/env bash
# Builds chunkrt, the inference bench and the GPU test binary with `--features cuda` on a machine
# without a GPU, and packs them for a GPU machine that has the NVIDIA driver and the CUDA 13
# libraries but no Rust toolchain:
#
#   bash scripts/gpu-package.sh [OUT_DIR]      # default OUT_DIR: .gpu (ignored by git)
#
# OUT_DIR then holds chunkrt.xz, inference.xz, policy_device.xz and run.sh (scripts/gpu-run.sh).
# Copy OUT_DIR and tests/data to the GPU machine (or carry them along with the checkout) and run
# `bash OUT_DIR/run.sh` from the checkout's root there. The build reuses CARGO_TARGET_DIR
# (default: ../target-cuda beside the checkout, so that the first, ~45-minute build of candle's
# CUDA kernels survives a fresh clone).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-.gpu}
prefix=${CHUNKRT_CUDA_PREFIX:-$HOME/.cache/chunkrt-cuda13}
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$(cd .. && pwd)/target-cuda}

bash scripts/cuda-toolkit.sh "$prefix" >/dev/null
eval "$(bash scripts/cuda-toolkit.sh --env "$prefix")"

echo "gpu-package: building with --features cuda into $CARGO_TARGET_DIR" >&2
cargo build --release --features cuda --bin chunkrt
# the bench and the test binary, in the same profile and feature set (no candle rebuild)
bench=$(cargo bench --features cuda --bench inference --no-run --message-format=json 2>/dev/null \
  | sed -n 's/.*"executable":"\([^"]*inference-[^"]*\)".*/\1/p' | tail -n 1)
test=$(cargo test --release --features cuda --test policy_device --no-run --message-format=json 2>/dev/null \
  | sed -n 's/.*"executable":"\([^"]*policy_device-[^"]*\)".*/\1/p' | tail -n 1)
[ -n "$bench" ] && [ -n "$test" ] || { echo "gpu-package: bench or test binary not found" >&2; exit 1; }

mkdir -p "$out"
for pair in "chunkrt:$CARGO_TARGET_DIR/release/chunkrt" "inference:$bench" "policy_device:$test"; do
  name=${pair%%:*}; src=${pair#*:}
  strip -o "$out/$name" "$src"
  xz -T0 -6 -f "$out/$name"
  echo "gpu-package: $out/$name.xz ($(du -h "$out/$name.xz" | cut -f1))" >&2
done
cp scripts/gpu-run.sh "$out/run.sh"
echo "gpu-package: done; on the GPU machine, from the checkout's root: bash $out/run.sh" >&2
