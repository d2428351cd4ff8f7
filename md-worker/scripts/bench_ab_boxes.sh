#!/bin/bash
# A/B of md-worker builds against LAMMPS on boxes, one thread / one process, interleaved run by
# run (LAMMPS, then each binary in turn, RUNS times), so every code sees the same machine load.
# Mishin Cu, CELLS^3 fcc cells (5: 500 atoms, 3: 108 atoms), fix deform + NVE (LAMMPS:
# md-worker/scripts/lammps_bench.in, 600 K start = 300 K after equipartition; md-worker: bench
# --boxes 16 --steps 200 --reps 5, 300 K, L_xx = 1e-3/ps).
# Usage: bash md-worker/scripts/bench_ab_boxes.sh CELLS LAMMPS_STEPS RUNS BIN [BIN ...]
#   e.g. bash md-worker/scripts/bench_ab_boxes.sh 5 2000 5 /tmp/md-worker-before target/release/md-worker
#   (each BIN an `md-worker` built with cargo build --release -p md-worker at the commit to compare;
#   MSCALE_MD_SIMD in the environment picks the kernel path of every binary).
# Needs lmp (bash deploy/setup.sh lammps), python3, /usr/bin/time.
# Figures, ns per atom-step: wall (LAMMPS loop time; md-worker bench's median call) and CPU
# (user + sys of the whole process over its timed atom-steps; md-worker's includes building its
# boxes). The load average is printed with every run: on a shared machine the CPU figure is the
# fair one (the wall clock also counts other processes' time slices), and each code's fastest
# run's CPU figure is printed too (under load, CPU time still rises with the other processes'
# cache and core sharing; the fastest run is the least disturbed).
set -euo pipefail
[ $# -ge 4 ] || { sed -n 2,16p "$0" >&2; exit 2; }
CELLS=$1; LSTEPS=$2; RUNS=$3; shift 3
BINS=("$@")
for b in "${BINS[@]}"; do [ -x "$b" ] || { echo "not an executable: $b" >&2; exit 2; }; done
command -v lmp >/dev/null || { echo "lmp not found: bash deploy/setup.sh lammps" >&2; exit 2; }
NAT=$((4 * CELLS * CELLS * CELLS)); POT=md-worker/potentials/Cu_mishin1.eam.alloy; REPS=5
T=$(mktemp); trap 'rm -f "$T"' EXIT
echo "lmp -sf opt -in md-worker/scripts/lammps_bench.in -log none -var c $CELLS -var n $LSTEPS   ($NAT atoms)"
echo "BIN bench --potential $POT --lattice fcc --a0 3.615 --cells $CELLS --boxes 16 --steps 200 --reps $REPS --backend cpu --threads 1"
rows=()
for r in $(seq "$RUNS"); do
  load=$(cut -d' ' -f1 /proc/loadavg)
  lw=$(/usr/bin/time -o "$T" -f "%U %S" lmp -sf opt -in md-worker/scripts/lammps_bench.in -log none -var c "$CELLS" -var n "$LSTEPS" 2>&1 | grep "Loop time" | awk '{print $4}')
  line="$load $(awk -v n=$NAT -v s=$LSTEPS -v w="$lw" '{print w/(n*s)*1e9, ($1+$2)/(n*s)*1e9}' "$T")"
  for b in "${BINS[@]}"; do
    out=$(/usr/bin/time -o "$T" -f "%U %S" "$b" bench --potential $POT --lattice fcc --a0 3.615 --cells "$CELLS" --boxes 16 --steps 200 --reps $REPS --backend cpu --threads 1)
    line="$line $(python3 -c "import json,sys; d=json.loads(sys.argv[1]); t=open(sys.argv[2]).read().split(); print(d['simd'], d['ns_per_atom_step'], (float(t[0])+float(t[1]))/($REPS*d['atoms']*d['steps'])*1e9)" "$out" "$T")"
  done
  echo "run $r (load, then wall cpu ns/atom-step): $line"
  rows+=("$line")
done
echo "load after: $(cat /proc/loadavg)"
printf '%s\n' "${rows[@]}" | python3 -c '
import statistics as st, sys
bins = sys.argv[1:]
rows = [l.split() for l in sys.stdin if l.strip()]
med = lambda k: st.median(float(r[k]) for r in rows)
lo = lambda k: min(float(r[k]) for r in rows)
L, LC = med(1), med(2)
print(f"median of {len(rows)} runs (load {min(float(r[0]) for r in rows):.1f}-{max(float(r[0]) for r in rows):.1f}), ns/atom-step wall / cpu:")
print(f"  LAMMPS -sf opt, 1 process: {L:.0f} / {LC:.0f}   (cpu of the fastest run: {lo(2):.0f})")
for k, b in enumerate(bins):
    W, C = med(4 + 3 * k), med(5 + 3 * k)
    print(f"  {b} ({rows[0][3 + 3 * k]}, 1 thread): {W:.0f} / {C:.0f}  -> vs LAMMPS {L / W:.2f}x wall, {LC / C:.2f}x cpu"
          f"   (cpu of the fastest run: {lo(5 + 3 * k):.0f}, {lo(2) / lo(5 + 3 * k):.2f}x LAMMPS fastest)")
' "${BINS[@]}"
