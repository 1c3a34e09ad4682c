#!/bin/bash
# usage: loop.sh N OUTDIR : the FR3 test binary N times in a row beside one busy loop
n=$1; out=$2; mkdir -p $out
B=/tmp/blk/r2/ci/target/debug/deps/franka_sim-3eff33ea7562f900
cd /tmp/blk/r2/ci
(exec -a busyloop bash -c 'while :; do :; done') & busy=$!
echo "busy loop pid $busy, start $(date -u +%T)" > $out/loop.log
for i in $(seq 1 $n); do
  s=$(grep '^cpu ' /proc/stat)
  t0=$(date +%s)
  $B --nocapture --test-threads 1 > $out/suite_$i.txt 2>&1; rc=$?
  e=$(grep '^cpu ' /proc/stat)
  steal=$(python3 -c "a='$s'.split()[1:];b='$e'.split()[1:];d=[int(y)-int(x) for x,y in zip(a,b)];print('%.1f'%(100*d[7]/sum(d)))")
  res=$(grep "^test result" $out/suite_$i.txt)
  echo "run $i rc=$rc $(($(date +%s)-t0))s steal=${steal}% $res" >> $out/loop.log
done
kill $busy
echo "end $(date -u +%T)" >> $out/loop.log
