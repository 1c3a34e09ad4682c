#!/usr/bin/env bash
# Runs on the GPU machine (scripts/gpu-package.sh packs it next to the binaries as .gpu/run.sh):
# unpacks them, finds the CUDA 13 libraries, and runs the GPU checks and benchmarks as steps, each
# under its own time limit, from the checkout's root (tests/data must be there):
#
#   bash .gpu/run.sh [STEP...]     # default: every step, in this order, within --budget
#
#   fixtures  `chunkrt sample --device cuda` on both openpi fixtures, f32 (within 1e-4 of the RMS)
#             and bf16 (within 3 %), compared in the binary (`--compare`)
#   tests     the GPU test binary (tests/policy_device.rs), if packed
#   pi05      full-size π0.5 bf16: every phase and the f32 accuracy check
#   serve     `chunkrt serve --device cuda` with a full-size π0.5 (random weights, written here)
#             answering one unmodified openpi-client (carried wheels in .whl/) on loopback
#   demo      `chunkrt demo` with the policy on cuda (config/default.toml, device = "cuda")
#   pi0       full-size π0 bf16
#   configs   the bench configurations (pi05_bench, pi0_bench) in f32
#   profile   ncu's kernel times of one eager π0.5 sample (CSV)
#
# Every step's output goes to its own file under /tmp/chunkrt-gpu-raw, packed after each step
# into $OUT/raw.tgz (the device tool brings back at most 8 files); the console shows each step's
# tail. CHUNKRT_GPU_BUDGET (s, default 330): a step is skipped once that much time has passed.
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
out=${OUT:-/tmp/chunkrt-gpu}
raw=/tmp/chunkrt-gpu-raw
budget=${CHUNKRT_GPU_BUDGET:-330}
steps=("$@")
[ ${#steps[@]} -gt 0 ] || steps=(fixtures tests pi05 serve demo pi0 configs profile)
start=$SECONDS
mkdir -p "$out" "$raw" /tmp/chunkrt-bin
for n in chunkrt policy_device; do
  [ -f "$here/$n.xz" ] || continue
  xz -dc "$here/$n.xz" > "/tmp/chunkrt-bin/$n" && chmod +x "/tmp/chunkrt-bin/$n"
done
B=/tmp/chunkrt-bin/chunkrt
# the driver's libcuda, and the CUDA 13 runtime libraries from wherever they are installed
libs=/usr/local/nvidia/lib64
for d in /usr/local/cuda/lib64 /usr/local/cuda-13.0/lib64 \
         $(ls -d /opt/*/.venv/lib/python3*/site-packages/nvidia/cu13/lib 2>/dev/null) \
         $(python3 -c 'import nvidia, os; print(os.path.join(nvidia.__path__[0], "cu13", "lib"))' 2>/dev/null); do
  [ -d "$d" ] && libs="$libs:$d"
done
export LD_LIBRARY_PATH="$libs:$here/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
export CHUNKRT_EXE=$B RUST_BACKTRACE=1
# the plots find their font through fontconfig; an image without a configuration still has
# DejaVu Sans in matplotlib's package, if matplotlib is there
if ! fc-match sans-serif >/dev/null 2>&1; then
  ttf=$(python3 -c 'import matplotlib, os; print(os.path.join(os.path.dirname(matplotlib.__file__), "mpl-data", "fonts", "ttf"))' 2>/dev/null)
  if [ -n "$ttf" ] && [ -d "$ttf" ]; then
    printf '<?xml version="1.0"?><fontconfig><dir>%s</dir><cachedir>/tmp/fc-cache</cachedir><alias><family>sans-serif</family><prefer><family>DejaVu Sans</family></prefer></alias></fontconfig>\n' "$ttf" > /tmp/chunkrt-fonts.conf
    export FONTCONFIG_FILE=/tmp/chunkrt-fonts.conf
  fi
fi
{ nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv; nproc; } | tee "$raw/gpu.txt"
if ldd "$B" | grep "not found"; then
  echo "gpu-run: missing libraries (LD_LIBRARY_PATH=$LD_LIBRARY_PATH)" >&2; exit 1
fi

pack() { tar czf "$out/raw.tgz" -C "$raw" . 2>/dev/null; }
failed=()
# step NAME LIMIT_S CMD...: runs CMD under its limit, output to $raw/NAME.txt, its tail shown
run() {
  local name=$1 limit=$2 rc; shift 2
  echo "== [$((SECONDS - start)) s] $name (limit $limit s): $*"
  timeout -k 5 "$limit" "$@" > "$raw/$name.txt" 2>&1; rc=$?
  tail -n "${TAIL:-25}" "$raw/$name.txt"
  echo "== $name: exit $rc after $((SECONDS - start)) s"
  [ $rc -eq 0 ] || failed+=("$name($rc)")
  pack
  return $rc
}

fixtures() {
  for f in pi05_tiny pi0_tiny; do
    for p in f32 bf16; do
      local tol="0.03 --actions-only"; [ $p = f32 ] && tol=1e-4
      # shellcheck disable=SC2086
      TAIL=6 run "fixture_${f}_$p" 60 "$B" sample --device cuda --precision $p \
        --checkpoint tests/data/$f --inputs tests/data/$f/inputs.safetensors \
        --output "$raw/${f}_$p.safetensors" --compare tests/data/$f/outputs.safetensors --rel-tol $tol
    done
  done
}

tests() {
  [ -x /tmp/chunkrt-bin/policy_device ] || { echo "== tests: no policy_device binary packed"; return; }
  TAIL=40 run tests 150 /tmp/chunkrt-bin/policy_device --test-threads 1 --nocapture
}

bench() { # NAME PRESET LIMIT EXTRA...
  local name=$1 preset=$2 limit=$3; shift 3
  TAIL=40 run "$name" "$limit" "$B" bench-inference --device cuda --preset "$preset" --calls 30 --warmup 5 "$@"
}

pi05() {
  bench bench_pi05 pi05 200 --precision bf16 --check-f32
}

pi0() {
  bench bench_pi0 pi0 150 --precision bf16
}

configs() {
  bench bench_pi05_bench_f32 pi05_bench 60 --precision f32
  bench bench_pi0_bench_f32 pi0_bench 60 --precision f32
}

demo() {
  sed 's/^device = "cpu"/device = "cuda"/' config/default.toml > config/default_cuda.toml
  grep -q '^device = "cuda"' config/default_cuda.toml || { echo "== demo: could not set the device"; return; }
  TAIL=20 run demo 100 "$B" demo --config config/default_cuda.toml --episodes 1 --out /tmp/chunkrt-demo
  cp /tmp/chunkrt-demo/demo.png "$raw/demo.png" 2>/dev/null
  pack
}

serve() {
  local ck=/tmp/pi05_random port=8765 site=/tmp/site
  TAIL=3 run write_checkpoint 90 "$B" bench-inference --preset pi05 --precision bf16 --write-checkpoint "$ck" || return
  if ! python3 -c 'import openpi_client' 2>/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl \
      > "$raw/pip.txt" 2>&1 || { echo "== serve: pip could not install .whl/"; cat "$raw/pip.txt"; }
    export PYTHONPATH=$site${PYTHONPATH:+:$PYTHONPATH}
  fi
  "$B" serve --checkpoint "$ck" --device cuda --precision bf16 --port $port --log-every 5 --duration 150 \
    > "$raw/serve_server.txt" 2>&1 &
  local pid=$!
  PYTHONUNBUFFERED=1 TAIL=12 run serve_client 150 python3 tools/python/openpi_peer.py latency \
    --url ws://127.0.0.1:$port --state-dim 4 --warmup 5 --requests 50 --wait 120
  kill -INT $pid 2>/dev/null; sleep 2; kill -9 $pid 2>/dev/null
  echo "-- server log (tail)"; tail -n 15 "$raw/serve_server.txt"
  pack
}

profile() {
  local ncu
  ncu=$(command -v ncu || ls /usr/local/cuda*/bin/ncu /opt/nvidia/nsight-compute/*/ncu 2>/dev/null | head -n 1)
  [ -n "$ncu" ] || { echo "== profile: no ncu"; return; }
  TAIL=5 run profile 120 "$ncu" --profile-from-start off --metrics gpu__time_duration.sum --csv --page raw \
    --log-file "$raw/profile_ncu.log" -o /tmp/prof "$B" bench-inference --device cuda --preset pi05 \
    --precision bf16 --profile
  "$ncu" --import /tmp/prof.ncu-rep --csv --page raw --metrics gpu__time_duration.sum > "$raw/profile_kernels.csv" 2>&1
  # per kernel name: launches and total time, largest first
  python3 - "$raw/profile_kernels.csv" > "$raw/profile_summary.txt" 2>&1 <<'PY'
import csv, collections, sys
rows = list(csv.reader(open(sys.argv[1])))
head = next(i for i, r in enumerate(rows) if "Kernel Name" in r)
cols = rows[head]
name, dur = cols.index("Kernel Name"), cols.index("gpu__time_duration.sum")
unit = rows[head + 1][dur] if len(rows) > head + 1 else ""
tot, cnt = collections.Counter(), collections.Counter()
for r in rows[head + 2:]:
    try:
        v = float(r[dur].replace(",", ""))
    except (ValueError, IndexError):
        continue
    tot[r[name][:90]] += v
    cnt[r[name][:90]] += 1
all_ = sum(tot.values())
print(f"{sum(cnt.values())} kernels, {all_:.0f} {unit} in all")
for k, v in tot.most_common(45):
    print(f"{v:12.0f} {unit} {100 * v / all_:5.1f} %  {cnt[k]:5d} x  {k}")
PY
  head -n 20 "$raw/profile_summary.txt"
  pack
}

for s in "${steps[@]}"; do
  if [ $((SECONDS - start)) -ge "$budget" ]; then
    echo "== $s: SKIPPED (the budget of $budget s has passed)"; failed+=("$s(skipped)"); continue
  fi
  "$s"
done
pack
echo "== done in $((SECONDS - start)) s; failed or skipped: ${failed[*]:-none}"
[ ${#failed[@]} -eq 0 ]
