#!/usr/bin/env bash
# Error against wall time over every 1D scheme (issue 17 "Error against run time"): the
# manufactured solution at G = 0.1 and the weak and strong isothermal shock tubes. Run from the
# repository root after `cargo build --release -p orchestrator --bin mscale`:
#   bash continuum/docs/error-vs-time/run.sh [OUT]      (OUT default runs/error-vs-time)
# Each scene needs three reports, because `report error-vs-time` sweeps one setting per key and
# the schemes need different ones: sub-points only for ddmp-subpoints, the leapfrog for impm.
# The merged tables (one header, rows in sweep order) are written next to this script.
set -euo pipefail
cd "$(dirname "$0")/../../.."
bin=${MSCALE:-target/release/mscale}
out=${1:-runs/error-vs-time}
here=continuum/docs/error-vs-time
cells="--sweep domain.cells=[125],[250],[500],[1000]"
report() { "$bin" report error-vs-time "$@" 2>&1 | tail -1; }
merge() { # merge NAME DIR... : the first report's header, then every report's rows
  local name=$1; shift
  { head -1 "$1/report.csv"; for d in "$@"; do tail -n +2 "$d/report.csv"; done; } |
    sed 's#,runs/[0-9]*$##; s#,run_dir$##' > "$here/$name.csv"
}
m="--sweep domain.cells=[32],[128],[512],[2048]"
report scenes/mms-1d.toml --sweep scheme.method=mpm,ugimp,cpgimp,cpdi,cpdi-improved,impm,ddmp $m --out "$out/mms-a"
report scenes/mms-1d.toml --sweep scheme.method=ddmp-subpoints $m --set scheme.sub_points=8 --out "$out/mms-b"
merge mms-1d-g0.1 "$out/mms-a" "$out/mms-b"
cp "$out/mms-a/report.png" "$here/mms-1d-g0.1.png"
m2="--sweep domain.cells=[8,8],[16,16],[32,32],[64,64]"
report scenes/mms-2d.toml --sweep scheme.method=mpm,ugimp,cpgimp,cpdi1,cpdi2,cpdi-improved,impm,ddmp $m2 --out "$out/mms2d-a"
report scenes/mms-2d.toml --sweep scheme.method=ddmp-subpoints $m2 --sweep scheme.sub_points=4,8,16 --out "$out/mms2d-b"
merge mms-2d-g0.1 "$out/mms2d-a"
merge mms-2d-g0.1-subpoints "$out/mms2d-b"   # one more column (the sub-points swept)
cp "$out/mms2d-a/report.png" "$here/mms-2d-g0.1.png"
for tube in weak strong; do
  s=scenes/shock-tube-$tube.toml
  report $s --sweep scheme.method=mpm,ugimp,cpgimp,cpdi,cpdi-improved,ddmp $cells --set scheme.sub_points=1 --out "$out/$tube-a"
  report $s --sweep scheme.method=ddmp-subpoints $cells --out "$out/$tube-b"
  report $s --sweep scheme.method=impm $cells --set scheme.sub_points=1 --set scheme.integrator=leapfrog --out "$out/$tube-c"
  merge shock-tube-$tube "$out/$tube-a" "$out/$tube-b" "$out/$tube-c"
  cp "$out/$tube-a/report.png" "$here/shock-tube-$tube.png"
done
