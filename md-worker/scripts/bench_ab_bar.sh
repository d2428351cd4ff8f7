#!/bin/bash
# A/B on the 43,200-atom bar, 1 thread: lmp -sf opt (1 process) | /tmp/h15_md_old | /tmp/h15_md_fpi (release builds before/after). Usage: bash md-worker/scripts/bench_ab_bar.sh STEPS RUNS
STEPS=$1; RUNS=$2; NAT=43200; OUT=$(mktemp -d); T=$OUT/time
timed() { /usr/bin/time -o "$T" -f "%e %U %S" "$@" > "$OUT/log" 2>&1; awk '{print $1, $2 + $3}' "$T"; }
md() {
  local B=$1
  D="$B direct --potential md-worker/potentials/Cu_mishin1.eam.alloy --a0 3.615 --cells 300,6,6 --region 0:542.25:-0.05 --wall 10 --dt 0.001 --out $OUT/bar.csv --threads 1"
  read -r w0 c0 < <(timed $D --steps 0 --every 1)
  read -r w1 c1 < <(timed $D --steps $STEPS --every $STEPS)
  python3 -c "import sys; w0,c0,w1,c1=map(float,sys.argv[1:]); n=$NAT*$STEPS; print('%.0f %.0f' % ((w1-w0)/n*1e9, (c1-c0)/n*1e9))" $w0 $c0 $w1 $c1
}
echo "load before: $(cat /proc/loadavg)"
for r in $(seq $RUNS); do
  read -r w c < <(timed lmp -sf opt -in md-worker/scripts/lammps_bar.in -log none -var n $STEPS)
  loop=$(grep "Loop time" "$OUT/log" | awk '{print $4}')
  l=$(python3 -c "n=$NAT*$STEPS; print('%.0f %.0f' % ($loop/n*1e9, $c/n*1e9))")
  echo "run $r (wall cpu ns/atom-step): lmp np1 $l | old 1t $(md /tmp/h15_md_old) | new 1t $(md /tmp/h15_md_fpi)"
done
echo "load after: $(cat /proc/loadavg)"
