#!/bin/bash
# The SO-101 expert's joint plan per seed: its success in simulated time (the env's own step) and
# replayed through chunkrt's controller into the real-time robot process (a scripted chunk source, a
# test double). Needs scripts/so101-env.sh's packages in python3 and a release build.
#   bash scripts/so101-replay-sweep.sh [SEEDS...]   (default 0..9)
# With TRACE_DIR set, the robot process writes each seed's physics trace there
# (so101_robot.py --trace; tools/python/so101_trace.py replays and compares one).
cd "$(dirname "$0")/.."
seeds="${*:-0 1 2 3 4 5 6 7 8 9}"
for seed in $seeds; do
  exp=$(python3 tools/python/so101_plan.py record --seed $seed --out "${TMPDIR:-/tmp}/so101_plan_$seed.json" | grep -o "success [A-Za-z]*")
  port=$((8800+seed)); ns=t/sweep$seed-$$
  python3 tools/python/so101_plan.py serve --plan "${TMPDIR:-/tmp}/so101_plan_$seed.json" --port $port > /dev/null 2>&1 & srv=$!
  sleep 1.5
  python3 tools/python/so101_robot.py --config ${CONFIG:-config/so101.toml} --namespace $ns --seed $seed --duration 16 ${TRACE_DIR:+--trace $TRACE_DIR/so101_trace_$seed.npz} > "${TMPDIR:-/tmp}/so101_robot_$seed.txt" 2>/dev/null & rob=$!
  sleep 0.5
  target/release/chunkrt run --config ${CONFIG:-config/so101.toml} --namespace $ns --remote ws://127.0.0.1:$port --duration 13 --log-every 0 > /dev/null 2>&1
  wait $rob; kill $srv 2>/dev/null
  r=$(grep "so101 summary" "${TMPDIR:-/tmp}/so101_robot_$seed.txt" | grep -oE "(success|time_to_success_s|tracking_error_p99|commands_far|block_carried)=[-0-9.]*" | tr '\n' ' ')
  echo "seed $seed expert_sim:$exp through_chunkrt: $r"
done
