#!/usr/bin/env bash
# The FR3 under faults injected on purpose (franka-sim 1.1.7, both of the FCI's checks enforced):
#   drops    LONG_S of scripted chunk switches (rtc, delays 0-8 action periods) with 1 % of the
#            driver's answers withheld at random (--drop-answers 0.01: a dropped UDP packet)
#   strict   SHORT_S of the same, 1 % withheld, against a robot 15 % stricter than the datasheet
#            (fr3_sim.py --strict 0.85)
#   stalls   SHORT_S of the same, the driver stopped (SIGSTOP) for 1-5 ms 100 times, then once for
#            60 ms (three times what the FCI allows)
#
#   soak     (only when SOAK_S is set) SOAK_S of the same, the driver stopped for 1-5 ms five times
#            a second (then once for 60 ms): a stall's late answer at every kind of cycle
#
#   bash benches/franka-faults.sh [SHORT_S [LONG_S]]     # defaults: 40 s, 600 s
#   RUNS="soak" SOAK_S=600 bash benches/franka-faults.sh  # only the stall soak
#
# Raw outputs (each process's log, the driver's summary and last 120 s of trace) go to $OUT
# (default benches/data/franka/<date>-faults); summary.md has one line per run. $EXE picks the
# binary (default: a release build). Needs scripts/franka-env.sh's venv.
set -euo pipefail
cd "$(dirname "$0")/.."
short=${1:-40}
long=${2:-600}
out=${OUT:-benches/data/franka/$(date -u +%Y-%m-%d)-faults}
mkdir -p "$out"
eval "$(bash scripts/franka-env.sh 2>/dev/null | sed -n 's/^\(CHUNKRT_FRANKA_PYTHON\|FR3_MJCF\)=/export &/p')"
if [ -z "${EXE:-}" ]; then
  cargo build --release --bin chunkrt >/dev/null
  EXE=target/release/chunkrt
fi
py=$CHUNKRT_FRANKA_PYTHON

# config/franka_fr3.toml with the scripted chunk source (a test double) sweeping delays 0-8
cfg=$out/scripted.toml
sed -e 's/strategy = "replace"/strategy = "rtc"/' -e 's/source = "remote"/source = "scripted"/' \
  -e 's/^\[openpi\]$/[policy.scripted]\ndelays = [0, 1, 2, 3, 4, 5, 6, 7, 8]\namplitude = 0.25\nfrequency_hz = 0.3\njump = 0.02\n\n[openpi]/' \
  config/franka_fr3.toml >"$cfg"

run() { # name host seconds "driver flags" "sim flags" stalls
  local name=$1 host=$2 secs=$3 dflags=$4 sflags=$5 stalls=$6 ns=fr3f$RANDOM
  local dir=$out/$name
  rm -rf "$dir"
  mkdir -p "$dir"
  echo "== $name: $secs s"
  # shellcheck disable=SC2086
  "$py" tools/python/fr3_sim.py --host "$host" --model "$FR3_MJCF" --no-gripper $sflags >"$dir/sim.log" 2>&1 &
  local sim=$!
  # shellcheck disable=SC2086
  "$EXE" franka --namespace "$ns" --config config/franka_fr3.toml --robot "$host" --realtime ignore \
    --gripper none --duration $((secs + 4)) --wait-for-robot 30 --status-every 10 \
    --trace "$dir/trace.csv" $dflags >"$dir/driver.log" 2>&1 &
  local drv=$!
  if [ "$stalls" -gt 0 ]; then
    "$py" - "$drv" "$stalls" >"$dir/stalls.log" 2>&1 <<'EOF' &
import os, signal, sys, time
pid, n = int(sys.argv[1]), int(sys.argv[2])
time.sleep(4)
made = 0
for k in range(n + 1):
    time.sleep(0.1 + (k * 7919 % 150) / 1e3)
    ms = 60.0 if k == n else 1.0 + k % 5
    try:
        os.kill(pid, signal.SIGSTOP)
        time.sleep(ms / 1e3)
        os.kill(pid, signal.SIGCONT)
        made += 1
    except ProcessLookupError:
        break
print(f"stalls={made} (the last 60 ms)")
EOF
  fi
  "$EXE" run --namespace "$ns" --config "$cfg" --duration "$secs" --log-every 0 >"$dir/controller.log" 2>&1 || true
  wait "$drv" || true
  kill -TERM "$sim" 2>/dev/null || true
  wait "$sim" 2>/dev/null || true
  wait || true
  grep -h 'franka summary\|franka-sim summary\|stalls=' "$dir"/*.log || true
}

runs=${RUNS:-drops strict stalls${SOAK_S:+ soak}}
for n in $runs; do
  case $n in
    drops) run drops 127.0.0.61 "$long" "--drop-answers 0.01" "" 0 ;;
    strict) run strict 127.0.0.62 "$short" "--drop-answers 0.01" "--strict 0.85" 0 ;;
    stalls) run stalls 127.0.0.63 "$short" "" "" 100 ;;
    soak) run soak 127.0.0.64 "${SOAK_S:?SOAK_S}" "" "" $((SOAK_S * 5)) ;;
    *) echo "unknown run: $n" >&2 && exit 2 ;;
  esac
done
{
  echo "# FR3 under faults ($(date -u +%FT%TZ), $(nproc) cores, $(uname -r), $EXE)"
  for n in $runs; do
    echo
    echo "## $n"
    grep -h 'franka summary\|franka-sim summary\|REFLEX\|stalls=' "$out/$n"/*.log | sed 's/^/    /'
  done
} >"$out/summary.md"
# the traces are for diagnosis (tens of MB), not for the record
rm -f "$out"/*/trace.csv
echo "wrote $out/summary.md"
