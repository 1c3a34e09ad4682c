#!/usr/bin/env bash
# Runs on the GPU machine (scripts/gpu-package.sh packs it next to the binaries): unpacks them,
# finds the CUDA 13 libraries, runs the GPU tests and the full-size benchmarks, and writes the
# logs to ${OUT:-/tmp/chunkrt-gpu}. From the checkout's root (tests/data must be there):
#
#   bash .gpu/run.sh [tests|bench|all]     # default: all
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
out=${OUT:-/tmp/chunkrt-gpu}
what=${1:-all}
mkdir -p "$out" /tmp/chunkrt-bin
for n in chunkrt policy_device; do
  [ -f "$here/$n.xz" ] || continue
  xz -dc "$here/$n.xz" > "/tmp/chunkrt-bin/$n" && chmod +x "/tmp/chunkrt-bin/$n"
done
# the driver's libcuda, and the CUDA 13 runtime libraries from wherever they are installed
libs=/usr/local/nvidia/lib64
for d in /usr/local/cuda/lib64 /usr/local/cuda-13.0/lib64 \
         $(ls -d /opt/*/.venv/lib/python3*/site-packages/nvidia/cu13/lib 2>/dev/null) \
         $(python3 -c 'import nvidia, os; print(os.path.join(nvidia.__path__[0], "cu13", "lib"))' 2>/dev/null); do
  [ -d "$d" ] && libs="$libs:$d"
done
export LD_LIBRARY_PATH="$libs:$here/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$out/gpu.txt"
if ldd /tmp/chunkrt-bin/chunkrt | grep "not found"; then
  echo "gpu-run: missing libraries (LD_LIBRARY_PATH=$LD_LIBRARY_PATH)" >&2; exit 1
fi
rc=0
if [ "$what" = tests ] || [ "$what" = all ]; then
  # the fixtures on the GPU through the CLI (f32 within 1e-4 of the RMS, bf16 within 3 %), then
  # the GPU tests if packed
  for f in pi05_tiny pi0_tiny; do
    for p in f32 bf16; do
      tol="0.03 --actions-only"; [ $p = f32 ] && tol=1e-4
      /tmp/chunkrt-bin/chunkrt sample --device cuda --precision $p --checkpoint tests/data/$f \
        --inputs tests/data/$f/inputs.safetensors --output "$out/${f}_$p.safetensors" \
        2>&1 | tee -a "$out/tests.log" || rc=1
      echo "== $f $p vs openpi" | tee -a "$out/tests.log"
      python3 scripts/gpu-compare.py tests/data/$f/outputs.safetensors "$out/${f}_$p.safetensors" \
        --rel-tol $tol 2>&1 | tee -a "$out/tests.log" || rc=1
    done
  done
  if [ -x /tmp/chunkrt-bin/policy_device ]; then
    /tmp/chunkrt-bin/policy_device --test-threads 1 --nocapture 2>&1 | tee -a "$out/tests.log" || rc=1
  fi
fi
if [ "$what" = bench ] || [ "$what" = all ]; then
  for p in pi05 pi0; do
    /tmp/chunkrt-bin/chunkrt bench-inference --device cuda --preset "$p" --precision bf16 --calls 30 --warmup 5 \
      2>&1 | tee "$out/bench_$p.txt" || rc=1
  done
  for p in pi05_bench pi0_bench; do
    /tmp/chunkrt-bin/chunkrt bench-inference --device cuda --preset "$p" --precision f32 --calls 30 --warmup 5 \
      2>&1 | tee "$out/bench_$p.txt" || rc=1
  done
fi
exit $rc
