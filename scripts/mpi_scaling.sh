#!/usr/bin/env bash
# Strong scaling of the continuum over MPI ranks against one process (1 and 2 threads), the
# forms interleaved, medians of ROUNDS (continuum/README.md "MPI", measured figures there).
#   scripts/mpi_scaling.sh MSCALE [2d|2d-jet|3d|3d-large] [ROUNDS] [mscale run options...]
# (options after ROUNDS are appended to the layout's, e.g. --set scheme.end_time=16e-12 for a
# longer run: a later --set of the same key wins)
# MSCALE: an mscale built with --features mpi. Time per step = summary.json
# time_breakdown_s.continuum / steps (rank 0); MSCALE_MPI_STATS gives each rank's collectives.
set -euo pipefail
M="${1:?usage: scripts/mpi_scaling.sh MSCALE [2d|2d-jet|3d|3d-large] [ROUNDS] [mscale run options]}"
LAYOUT="${2:-2d}"
ROUNDS="${3:-5}"
shift $(( $# < 3 ? $# : 3 ))
cd "$(dirname "$0")/.."
OUT="$(mktemp -d)"
trap 'rm -rf "$OUT"' EXIT
S=(--set output.snapshots=0 --set output.particles=false --set output.vtk=false --set output.plots=false)
SCENE=scenes/mms-2d.toml
case "$LAYOUT" in
  # The jet layout of `cargo bench -p continuum --bench step` (Dhakal Ch. 7): 100 x 50 cells
  # over 144 x 72 nm, 2 x 2 points a cell, the 36 nm notch: 18,750 points, 8 sub-points,
  # linear elastic (E 130 GPa, nu 0.34), tensor viscosity, at 2.5 km/s onto a fixed wall; 51 steps.
  2d-jet) SCENE=scenes/cu-notch-jet-2d.toml
          S+=(--set 'domain.max=[144e-9,72e-9]' --set 'domain.cells=[100,50]' --set 'bodies.copper.max=[144e-9,72e-9]'
          --set 'bodies.copper.notch={center=72e-9,width=36e-9,depth=36e-9}'
          --set 'bodies.copper.material={law="linear-elastic",youngs_modulus=130e9,poisson_ratio=0.34}'
          --set scheme.particles_per_cell=2 --set scheme.sub_points=8 --set 'boundary.x_min="reflective"'
          --set 'boundary.x_max="reflective"' --set 'boundary.y_min="fixed"' --set scheme.end_time=4e-12) ;;
  # 16,384 points, 8 sub-points, 48 steps (the stage 1 layout, close to the jet bench's 18,750 x 8).
  2d) S+=(--set 'domain.cells=[64,64]' --set 'scheme.method="ddmp-subpoints"' --set scheme.sub_points=8 --set scheme.end_time=0.003) ;;
  # The mms cube on 16 x 16 x 32 cells, 65,536 points, cpdi1, 4 steps.
  3d) S+=(--set domain.dimension=3 --set 'domain.min=[0.0,0.0,0.0]' --set 'domain.max=[1.0,1.0,1.0]' --set 'domain.cells=[16,16,32]'
          --set 'bodies.bar.min=[0.0,0.0,0.0]' --set 'bodies.bar.max=[1.0,1.0,1.0]' --set 'boundary.z_min="roller"'
          --set 'boundary.z_max="roller"' --set scheme.end_time=0.0005) ;;
  # The same cube on 40 x 40 x 80 cells: 1,024,000 points, 4 steps.
  3d-large) S+=(--set domain.dimension=3 --set 'domain.min=[0.0,0.0,0.0]' --set 'domain.max=[1.0,1.0,1.0]' --set 'domain.cells=[40,40,80]'
          --set 'bodies.bar.min=[0.0,0.0,0.0]' --set 'bodies.bar.max=[1.0,1.0,1.0]' --set 'boundary.z_min="roller"'
          --set 'boundary.z_max="roller"' --set scheme.end_time=0.0002) ;;
  *) echo "layout $LAYOUT: 2d, 2d-jet, 3d or 3d-large" >&2; exit 2 ;;
esac
S+=("$@")
export RUST_LOG=warn OMPI_MCA_btl_vader_single_copy_mechanism=none OMPI_MCA_mpi_yield_when_idle=1 MSCALE_MPI_STATS=1
MPIRUN=(mpirun --allow-run-as-root --oversubscribe -np 2)
for round in $(seq "$ROUNDS"); do
  for form in one thread2 rank2 rank2-rebalance10; do
    d="$OUT/$form-$round"
    case $form in
      one) RAYON_NUM_THREADS=1 "$M" run "$SCENE" --out "$d" "${S[@]}" > "$d.log" 2>&1 ;;
      thread2) RAYON_NUM_THREADS=2 "$M" run "$SCENE" --out "$d" "${S[@]}" > "$d.log" 2>&1 ;;
      rank2) RAYON_NUM_THREADS=1 "${MPIRUN[@]}" "$M" run "$SCENE" --out "$d" "${S[@]}" > "$d.log" 2>&1 ;;
      rank2-rebalance10) RAYON_NUM_THREADS=1 "${MPIRUN[@]}" "$M" run "$SCENE" --out "$d" "${S[@]}" --rebalance-every 10 > "$d.log" 2>&1 ;;
    esac
    python3 - "$d" "$form" <<'PY'
import json, re, sys
d, form = sys.argv[1], sys.argv[2]
s = json.load(open(d + "/summary.json"))
ms = 1000 * s["time_breakdown_s"]["continuum"] / s["steps"]
# One line per rank ("mscale: rank R of N: C collectives, B bytes sent, ... S s inside them");
# the ranks' lines may interleave on the shared stderr, so match them anywhere.
text = open(d + ".log").read()
stats = re.findall(r"rank (\d+) of \d+: \d+ collectives, (\d+) bytes sent, \d+ bytes received, ([0-9.]+) s inside", text)
stats.sort()
inside = [float(t) * 1000 / s["steps"] for _, _, t in stats]
sent = [int(b) / s["steps"] for _, b, _ in stats]
r = s.get("ranks") or {}
print(f"{form} {ms:.2f} ms/step digest {s['state_digest'][:12]} collectives/step/rank {[round(x, 2) for x in inside]} ms "
      f"sent/step/rank {[round(x / 1e3, 1) for x in sent]} kB points/rank {r.get('points_per_rank')} migrated {r.get('migrated_points')}")
PY
  done
  echo "# round $round: $(uptime)"
done
