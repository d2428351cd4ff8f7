#!/bin/bash
# md-worker direct (threads inside the bar) vs LAMMPS on the 43,200-atom Cu bar (300 x 6 x 6 fcc
# cells, left half pre-compressed 5 %, 10 A frozen walls, 0 K, 1 fs), interleaved run by run.
# Usage: bash md-worker/scripts/bench_direct_bar.sh [RUNS] [STEPS]   (from the repository root)
# Needs: cargo, lmp (bash deploy/setup.sh lammps), mpirun (bash deploy/setup.sh mpi), python3,
# /usr/bin/time. Each run, in turn: md-worker direct --threads 1; --threads 2; mpirun -np 2 lmp
# -sf opt; lmp -sf opt (1 process). md-worker's ns/atom-step are (T(STEPS) - T(0)) / (atoms * STEPS)
# (the bar's set-up and first force evaluation subtracted), wall and CPU (user + sys); LAMMPS's
# wall is its loop time, its CPU the process's user + sys over the atom-steps.
set -euo pipefail
RUNS=${1:-5}
STEPS=${2:-200}
NAT=43200
# MD=path/to/md-worker runs that binary; unset, the release build of this checkout.
if [ -z "${MD:-}" ]; then
  export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
  cargo build --release -q -p md-worker
  MD="$CARGO_TARGET_DIR/release/md-worker"
fi
OUT=$(mktemp -d)
DIRECT="$MD direct --potential md-worker/potentials/Cu_mishin1.eam.alloy --a0 3.615 --cells 300,6,6 --region 0:542.25:-0.05 --wall 10 --dt 0.001 --out $OUT/bar.csv"
LMP="lmp -sf opt -in md-worker/scripts/lammps_bar.in -log none -var n $STEPS"
MPI="mpirun --allow-run-as-root --oversubscribe -np 2"
echo "commands:"
echo "  $DIRECT --steps $STEPS --every $STEPS --threads 1|2   (and --steps 0 for the set-up)"
echo "  $MPI $LMP"
echo "  $LMP"
echo "load before: $(cat /proc/loadavg)"
T=$OUT/time
# wall and cpu seconds of a command
timed() { /usr/bin/time -o "$T" -f "%e %U %S" "$@" > "$OUT/log" 2>&1; awk '{print $1, $2 + $3}' "$T"; }
md() {
  local t=$1
  read -r w0 c0 < <(timed $DIRECT --steps 0 --every 1 --threads "$t")
  read -r w1 c1 < <(timed $DIRECT --steps "$STEPS" --every "$STEPS" --threads "$t")
  python3 -c "import sys; w0,c0,w1,c1=map(float,sys.argv[1:]); n=$NAT*$STEPS; print((w1-w0)/n*1e9, (c1-c0)/n*1e9)" "$w0" "$c0" "$w1" "$c1"
}
lmp_run() {
  read -r w c < <(timed "$@")
  local loop
  loop=$(grep "Loop time" "$OUT/log" | awk '{print $4}')
  python3 -c "n=$NAT*$STEPS; print($loop/n*1e9, $c/n*1e9)"
}
rows=()
for r in $(seq "$RUNS"); do
  a=$(md 1)
  b=$(md 2)
  c=$(lmp_run $MPI $LMP)
  d=$(lmp_run $LMP)
  echo "run $r (load $(cut -d" " -f1 /proc/loadavg); wall, cpu ns/atom-step): direct 1t $a | direct 2t $b | lmp np2 $c | lmp np1 $d"
  rows+=("$a $b $c $d")
done
echo "load after: $(cat /proc/loadavg)"
rm -rf "$OUT"
printf '%s\n' "${rows[@]}" | python3 -c '
import statistics as st, sys
rows = [[float(x) for x in l.split()] for l in sys.stdin if l.strip()]
med = lambda k: st.median(r[k] for r in rows)
names = ["md-worker direct 1 thread", "md-worker direct 2 threads", "LAMMPS -sf opt mpirun -np 2", "LAMMPS -sf opt 1 process"]
print(f"median of {len(rows)} runs, ns/atom-step (wall / cpu):")
for i, n in enumerate(names):
    print(f"  {n}: {med(2*i):.0f} / {med(2*i+1):.0f}")
print(f"  2 threads vs 1 thread (wall): {med(0)/med(2):.2f}x; md-worker 2 threads vs LAMMPS np 2 (wall): {med(4)/med(2):.2f}x")
'
