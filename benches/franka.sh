#!/usr/bin/env bash
# The Franka FR3 through FCI on loopback (franka-sim with both checks enforced): the round trip
# robot state -> driver -> controller tick -> command -> driver, idle and with both cores loaded,
# and a long run with chunk switches (the command success rate and the reflex count).
#
#   bash benches/franka.sh [SHORT_S [LONG_S]]      # defaults: 120 s each setting, 600 s long
#
# Each setting is `chunkrt demo --config config/franka_fr3.toml` (simulator, driver, camera,
# openpi's own server with the scripted DROID policy, controller); the loaded one adds one busy
# process per core at normal priority. Raw outputs (every process's log, the report, the plot)
# go to $OUT (default benches/data/franka/<date>). Needs scripts/franka-env.sh's venv, and the
# python3 on PATH with openpi-server (as .ci/run installs it).
set -euo pipefail
cd "$(dirname "$0")/.."
short=${1:-120}
long=${2:-600}
out=${OUT:-benches/data/franka/$(date -u +%Y-%m-%d)}
mkdir -p "$out"
eval "$(bash scripts/franka-env.sh 2>/dev/null | sed -n 's/^\(CHUNKRT_FRANKA_PYTHON\|FR3_MJCF\)=/export &/p')"
cargo build --release --bin chunkrt >/dev/null
exe=target/release/chunkrt

run() { # name seconds
  local name=$1 secs=$2
  rm -rf "$out/$name"
  mkdir -p "$out/$name"
  echo "== $name: $secs s"
  "$exe" demo --config config/franka_fr3.toml --episodes 1 --episode-seconds "$secs" \
    --log-dir "$out/$name/logs" --out "$out/$name" 2>&1 | tr '\r' '\n' | grep -v '^\[' >"$out/$name/demo.txt"
  # the per-cycle trace is for diagnosis, not for the record
  rm -f "$out/$name/logs/franka-trace.csv"
  grep -E 'franka summary|franka-sim summary|^\|' "$out/$name/demo.txt" || true
}

run idle "$short"
hogs=()
for _ in $(seq "$(nproc)"); do
  python3 -c 'while True: pass' &
  hogs+=($!)
done
trap 'kill "${hogs[@]}" 2>/dev/null || true' EXIT
run loaded "$short"
kill "${hogs[@]}" 2>/dev/null || true
run long "$long"
{
  echo "# FR3 through FCI on loopback ($(date -u +%FT%TZ), $(nproc) cores, $(uname -r))"
  for n in idle loaded long; do
    echo
    echo "## $n"
    grep -E '^\|' "$out/$n/demo.txt"
    grep -E 'franka summary|franka-sim summary|chunkrt summary' -A3 "$out/$n/demo.txt" | sed 's/^/    /'
  done
} >"$out/summary.md"
echo "wrote $out/summary.md"
