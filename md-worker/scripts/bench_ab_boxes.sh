#!/bin/bash
# Usage: bash md-worker/scripts/bench_ab_boxes.sh CELLS LAMMPS_STEPS RUNS, with /tmp/h15_md_old (the binary before) and /tmp/h15_md_fpi (after) built by cargo build --release -p md-worker at each commit.
# interleaved: LAMMPS -sf opt | md-worker old (main's avx512) | md-worker new; CPU ns/atom-step as bench_vs_lammps.sh
CELLS=$1; LSTEPS=$2; RUNS=$3
NAT=$((4*CELLS*CELLS*CELLS)); POT=md-worker/potentials/Cu_mishin1.eam.alloy; REPS=5
T=$(mktemp)
echo "load before: $(cat /proc/loadavg)"
for r in $(seq $RUNS); do
  lw=$(/usr/bin/time -o $T -f "%U %S" lmp -sf opt -in md-worker/scripts/lammps_bench.in -log none -var c $CELLS -var n $LSTEPS 2>&1 | grep "Loop time" | awk '{print $4}')
  l=$(awk -v n=$NAT -v s=$LSTEPS '{print ($1+$2)/(n*s)*1e9}' $T)
  line="lammps $l"
  for b in old fpi; do
    out=$(/usr/bin/time -o $T -f "%U %S" /tmp/h15_md_$b bench --potential $POT --lattice fcc --a0 3.615 --cells $CELLS --boxes 16 --steps 200 --reps $REPS --backend cpu --threads 1)
    c=$(python3 -c "import json,sys; d=json.loads(sys.argv[1]); t=open(sys.argv[2]).read().split(); print(d['ns_per_atom_step'], (float(t[0])+float(t[1]))/($REPS*d['atoms']*d['steps'])*1e9)" "$out" $T)
    line="$line $b $c"
  done
  echo "run $r (cpu ns/atom-step; md: wall cpu): $line"
done
echo "load after: $(cat /proc/loadavg)"
