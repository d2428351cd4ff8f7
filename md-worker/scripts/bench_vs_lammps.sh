#!/bin/bash
# md-worker vs LAMMPS throughput, side by side and interleaved (the machine may be shared:
# interleaving exposes both codes to the same load). Mishin Cu, CELLS^3 fcc cells (default 5:
# 500 atoms; 3: 108 atoms).
# Usage: bash md-worker/scripts/bench_vs_lammps.sh [RUNS] [CELLS] [LAMMPS_STEPS]   (from the repository root)
# Needs: cargo, lmp (bash deploy/setup.sh lammps), python3, /usr/bin/time.
# Each run, in turn: LAMMPS -sf opt; md-worker cpu 1 thread on the scalar path (MSCALE_MD_SIMD=scalar,
# the kernel before the SIMD work); md-worker cpu 1 thread on the default path; 2 threads.
# Two figures per code: wall ns/atom-step (LAMMPS loop time; md-worker bench's median call) and
# CPU ns/atom-step (user + sys of the whole process over its atom-steps, setup included; on a
# loaded machine the wall clock also counts other processes' time slices, CPU time does not).
set -euo pipefail
RUNS=${1:-5}
CELLS=${2:-5}
LSTEPS=${3:-2000}
NAT=$((4 * CELLS * CELLS * CELLS))
# MD=path/to/md-worker runs that binary; unset, the release build of this checkout.
if [ -z "${MD:-}" ]; then
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
  cargo build --release -q -p md-worker
  MD="$CARGO_TARGET_DIR/release/md-worker"
fi
POT=md-worker/potentials/Cu_mishin1.eam.alloy
REPS=5
MDB="$MD bench --potential $POT --lattice fcc --a0 3.615 --cells $CELLS --boxes 16 --steps 200 --reps $REPS --backend cpu"
LMP="lmp -sf opt -in md-worker/scripts/lammps_bench.in -log none -var c $CELLS -var n $LSTEPS"
echo "commands:"
echo "  $LMP   ($NAT atoms, $LSTEPS steps; wall ns/atom-step = loop time / ($NAT * $LSTEPS) * 1e9)"
echo "  MSCALE_MD_SIMD=scalar $MDB --threads 1"
echo "  $MDB --threads 1"
echo "  $MDB --threads 2"
echo "load before: $(cat /proc/loadavg)"
T=$(mktemp)
cpu() { awk '{print $1 + $2}' "$T"; }
# md-worker: wall median from its JSON, CPU over (REPS + 1) calls (open: one force evaluation).
md() {
  local out
  out=$(/usr/bin/time -o "$T" -f "%U %S" env "$@")
  python3 -c "import json,sys; d=json.loads(sys.argv[1]); c=float(sys.argv[2]); print(d['simd'], d['ns_per_atom_step'], c / ($REPS * d['atoms'] * d['steps']) * 1e9)" "$out" "$(cpu)"
}
rows=()
for r in $(seq "$RUNS"); do
  lw=$(/usr/bin/time -o "$T" -f "%U %S" $LMP 2>&1 | grep "Loop time" | awk '{print $4}')
  l="lammps $(python3 -c "print($lw / ($NAT * $LSTEPS) * 1e9, $(cpu) / ($NAT * $LSTEPS) * 1e9)")"
  s=$(md MSCALE_MD_SIMD=scalar $MDB --threads 1)
  a=$(md MSCALE_MD_SIMD=auto $MDB --threads 1)
  b=$(md MSCALE_MD_SIMD=auto $MDB --threads 2)
  echo "run $r (wall, cpu ns/atom-step): $l | 1t $s | 1t $a | 2t $b"
  rows+=("$l $s $a $b")
done
echo "load after: $(cat /proc/loadavg)"
rm -f "$T"
printf '%s\n' "${rows[@]}" | python3 -c '
import statistics as st, sys
rows = [l.split() for l in sys.stdin if l.strip()]
# lammps W C | path W C | path W C | path W C
med = lambda k: st.median(float(r[k]) for r in rows)
L, LC = med(1), med(2)
names = [("md-worker 1 thread, " + rows[0][3], 4, 5), ("md-worker 1 thread, " + rows[0][6], 7, 8), ("md-worker 2 threads, " + rows[0][9], 10, 11)]
print(f"median of {len(rows)} runs, ns/atom-step (wall / cpu): LAMMPS -sf opt 1 process {L:.0f} / {LC:.0f}")
for n, w, c in names:
    W, C = med(w), med(c)
    print(f"  {n}: {W:.0f} / {C:.0f}  -> throughput vs LAMMPS {L/W:.2f}x wall, {LC/C:.2f}x cpu")
'
