#!/usr/bin/env bash
# Builds chunkrt, the inference bench and the GPU test binary with `--features cuda` on a machine
# without a GPU, and packs them for a GPU machine that has the NVIDIA driver and the CUDA 13
# libraries but no Rust toolchain:
#
#   bash scripts/gpu-package.sh [--tests] [OUT_DIR]   # default OUT_DIR: .gpu (ignored by git)
#
# OUT_DIR then holds chunkrt.xz (with `chunkrt bench-inference`) and run.sh (scripts/gpu-run.sh);
# with --tests also policy_device.xz, the GPU test binary (tests/policy_device.rs). Building it
# pulls the dev-dependencies, which changes a feature set below candle: the first such build
# compiles candle's CUDA kernels once more (~30-45 min on 2 cores).
# Copy OUT_DIR and tests/data to the GPU machine (or carry them along with the checkout) and run
# `bash OUT_DIR/run.sh` from the checkout's root there. The build reuses CARGO_TARGET_DIR
# (default: ../target-cuda beside the checkout, so that the first, ~45-minute build of candle's
# CUDA kernels survives a fresh clone).
set -euo pipefail
cd "$(dirname "$0")/.."
with_tests=0
if [ "${1:-}" = "--tests" ]; then with_tests=1; shift; fi
out=${1:-.gpu}
prefix=${CHUNKRT_CUDA_PREFIX:-$HOME/.cache/chunkrt-cuda13}
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-$(cd .. && pwd)/target-cuda}

# installs the toolkit if needed (and `cargo fetch`es cudarc's sources for its libcuda stub)
bash scripts/cuda-toolkit.sh "$prefix" >/dev/null
eval "$(bash scripts/cuda-toolkit.sh --env "$prefix")"

echo "gpu-package: building with --features cuda into $CARGO_TARGET_DIR" >&2
cargo build --release --features cuda --bin chunkrt
pairs="chunkrt:$CARGO_TARGET_DIR/release/chunkrt"
if [ "$with_tests" = 1 ]; then
  test=$(cargo test --release --features cuda --test policy_device --no-run --message-format=json 2>/dev/null \
    | sed -n 's/.*"executable":"\([^"]*policy_device-[^"]*\)".*/\1/p' | tail -n 1)
  [ -n "$test" ] || { echo "gpu-package: the test binary was not built" >&2; exit 1; }
  pairs="$pairs policy_device:$test"
fi
mkdir -p "$out"
for pair in $pairs; do
  name=${pair%%:*}; src=${pair#*:}
  strip -o "$out/$name" "$src"
  xz -T0 -6 -f "$out/$name"
  echo "gpu-package: $out/$name.xz ($(du -h "$out/$name.xz" | cut -f1))" >&2
done
# the libraries the binary links beyond what a CUDA machine image has (the plots' fonts and
# PNG encoder); run.sh puts them last on the library path, so the machine's own come first
mkdir -p "$out/lib"
for l in $(ldd "$CARGO_TARGET_DIR/release/chunkrt" | awk '/fontconfig|freetype|png|brotli|expat/ {print $3}'); do
  cp -L "$l" "$out/lib/"
done
cp scripts/gpu-run.sh "$out/run.sh"
echo "gpu-package: done; on the GPU machine, from the checkout's root: bash $out/run.sh" >&2
