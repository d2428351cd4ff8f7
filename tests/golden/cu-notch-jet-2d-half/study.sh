#!/usr/bin/env bash
# Resolution and cost study of scenes/cu-notch-jet-2d-half.toml against its direct MD (issue 13
# §3, in the manner of the seed's Table 7.1). Run from the repository root after
#   cargo build --release -p orchestrator --bin mscale
# Usage:
#   bash tests/golden/cu-notch-jet-2d-half/study.sh run NAME [--set KEY=VALUE ...]
#       one coupled run to 10 ps into $STUDY_DIR/NAME (default runs/jet-study/NAME)
#   bash tests/golden/cu-notch-jet-2d-half/study.sh table [TIMES]
#       scores every run in $STUDY_DIR again against the committed reference at TIMES
#       (default [5.0,10.0]; `mscale report score`, the runs' own eq. 7.12) and prints
#       name,cells,points,atoms_per_box,sub_points,error at each time,md_atom_steps,
#       fraction of the direct MD's 4.146e9 atom-steps (345,495 atoms x 12,000 steps),wall_s
set -euo pipefail
cd "$(dirname "$0")/../../.."
bin=${MSCALE:-target/release/mscale}
dir=${STUDY_DIR:-runs/jet-study}
scene=scenes/cu-notch-jet-2d-half.toml
ref=tests/golden/cu-notch-jet-2d-half/direct-jet.csv
case "${1:-}" in
run)
  name=$2; shift 2
  mkdir -p "$dir"
  # Snapshots every continuum step's nearest to each ps; the run scores itself at the times the
  # reference has so far (its own `times_ps`); `table` scores it again at the study's times.
  "$bin" run "$scene" --set scheme.end_time=10e-12 --set output.snapshots=10 --set output.vtk=false \
    --out "$dir/$name" "$@" 2>&1 | tail -3
  ;;
table)
  times=${2:-[5.0,10.0]}
  python3 - "$bin" "$dir" "$ref" "$times" <<'PY'
import json, pathlib, subprocess, sys, tomllib
bin, d, ref, times = sys.argv[1:]
direct = 345495 * 12000
ts = json.loads(times)
print("name,cells,points,atoms_per_box,sub_points," + ",".join(f"syy_error_{t:g}ps" for t in ts) + ",md_atom_steps,of_direct_md,wall_s")
for run in sorted(pathlib.Path(d).iterdir()):
    s = json.load(open(run / "summary.json"))
    o = subprocess.run([bin, "report", "score", str(run), "--set", f"reference.times_ps={times}",
                        "--set", f"reference.profile={json.dumps(str(pathlib.Path(ref).resolve()))}"],
                       capture_output=True, text=True)
    if o.returncode != 0:
        print(f"{run.name}: not scored: {o.stderr.strip()}", file=sys.stderr); continue
    e = json.loads(o.stdout.split("\n", 1)[1])
    errs = [next(x["error"] for x in e["times"] if abs(x["time_ps"] - t) < 1e-6) for t in ts]
    sc = tomllib.loads((run / "scene.resolved.toml").read_text())
    cells = "x".join(str(c) for c in sc["domain"]["cells"])
    md = s["md"]
    atoms = md["bodies"]["copper"]["atoms_per_box"]
    print(f"{run.name},{cells},{s['points']},{atoms},{sc['scheme'].get('sub_points', '')},"
          + ",".join(f"{100*x:.2f}" for x in errs)
          + f",{md['atom_steps_done']:.3e},{md['atom_steps_done']/direct:.4f},{s['wall_seconds']:.0f}")
PY
  ;;
*) echo "usage: $0 run NAME [--set K=V ...] | table [TIMES]" >&2; exit 2 ;;
esac
