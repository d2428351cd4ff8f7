#!/bin/bash
# md-worker vs LAMMPS throughput, side by side and interleaved (the machine may be shared:
# interleaving exposes both codes to the same load). Mishin Cu, 500-atom boxes (5x5x5 fcc).
# Usage: bash md-worker/scripts/bench_vs_lammps.sh [RUNS]   (from the repository root)
# Needs: cargo, lmp (apt-get install -y lammps lammps-data), python3.
set -euo pipefail
RUNS=${1:-5}
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR:-target}
cargo build --release -q -p md-worker
MD="$CARGO_TARGET_DIR/release/md-worker"
POT=md-worker/potentials/Cu_mishin1.eam.alloy
MD1="$MD bench --potential $POT --lattice fcc --a0 3.615 --cells 5 --boxes 16 --steps 200 --threads 1 --backend cpu"
MD2="$MD bench --potential $POT --lattice fcc --a0 3.615 --cells 5 --boxes 16 --steps 200 --threads 2 --backend cpu"
LMP="lmp -sf opt -in md-worker/scripts/lammps_bench.in -log none -screen none"
echo "commands:"; echo "  $MD1"; echo "  $MD2"; echo "  $LMP   (500 atoms, 2000 steps; ns/atom-step = loop time / 1e6 * 1e9)"
echo "load before: $(cat /proc/loadavg)"
l=(); m1=(); m2=()
for r in $(seq "$RUNS"); do
  out=$(lmp -sf opt -in md-worker/scripts/lammps_bench.in -log none 2>&1 | grep "Loop time" | awk '{print $4}')
  l+=("$(python3 -c "print($out / (500 * 2000) * 1e9)")")
  m1+=("$($MD1 | python3 -c 'import json,sys; print(json.load(sys.stdin)["ns_per_atom_step"])')")
  m2+=("$($MD2 | python3 -c 'import json,sys; print(json.load(sys.stdin)["ns_per_atom_step"])')")
  echo "run $r: lammps ${l[-1]}  md-worker(1t) ${m1[-1]}  md-worker(2t) ${m2[-1]} ns/atom-step"
done
echo "load after: $(cat /proc/loadavg)"
python3 - "${l[*]}" "${m1[*]}" "${m2[*]}" <<'PY'
import statistics as s, sys
l, m1, m2 = ([float(x) for x in a.split()] for a in sys.argv[1:4])
L, M1, M2 = s.median(l), s.median(m1), s.median(m2)
print(f"median ns/atom-step: LAMMPS -sf opt 1 process {L:.0f}; md-worker cpu 1 thread {M1:.0f}; 2 threads {M2:.0f}")
print(f"throughput vs LAMMPS: 1 thread {L/M1:.2f}x, 2 threads {L/M2:.2f}x")
PY
