#!/usr/bin/env bash
# Error against wall time over every scheme (issue 17 "Error against run time"): the
# manufactured solution at G = 0.1 and the weak and strong isothermal shock tubes; and the heat
# and diffusion problems over schemes and the FLIP fraction beta (issue 19). Run from the
# repository root after `cargo build --release -p orchestrator --bin mscale`:
#   bash continuum/docs/error-vs-time/run.sh [OUT [PART ...]]   (OUT default runs/error-vs-time;
#   PART: mms, mms2d, mms2d-small, tubes, heat; default all)
# A scene may need several reports, because `report error-vs-time` sweeps one setting per key and
# the schemes need different ones: sub-points only for ddmp-subpoints, the leapfrog for impm.
# The merged tables (one header, rows in sweep order) are written next to this script.
set -euo pipefail
cd "$(dirname "$0")/../../.."
bin=${MSCALE:-target/release/mscale}
out=${1:-runs/error-vs-time}
shift || true
parts=${*:-mms mms2d mms2d-small tubes heat}
part() { [[ " $parts " == *" $1 "* ]]; }
here=continuum/docs/error-vs-time
cells="--sweep domain.cells=[125],[250],[500],[1000]"
report() { "$bin" report error-vs-time "$@" 2>&1 | tail -1; }
merge() { # merge NAME DIR... : the first report's header, then every report's rows
  local name=$1; shift
  { head -1 "$1/report.csv"; for d in "$@"; do tail -n +2 "$d/report.csv"; done; } |
    sed 's#,runs/[0-9]*$##; s#,run_dir$##' > "$here/$name.csv"
}
m="--sweep domain.cells=[32],[128],[512],[2048]"
if part mms; then
report scenes/mms-1d.toml --sweep scheme.method=mpm,ugimp,cpgimp,cpdi,cpdi-improved,impm,ddmp,tlmpm $m --out "$out/mms-a"
report scenes/mms-1d.toml --sweep scheme.method=ddmp-subpoints $m --set scheme.sub_points=8 --out "$out/mms-b"
merge mms-1d-g0.1 "$out/mms-a" "$out/mms-b"
cp "$out/mms-a/report.png" "$here/mms-1d-g0.1.png"
fi
m2="--sweep domain.cells=[8,8],[16,16],[32,32],[64,64]"
if part mms2d; then
report scenes/mms-2d.toml --sweep scheme.method=mpm,ugimp,cpgimp,cpdi1,cpdi2,cpdi-improved,cpdi1-improved,impm,ddmp,tlmpm $m2 --out "$out/mms2d-a"
report scenes/mms-2d.toml --sweep scheme.method=ddmp-subpoints $m2 --sweep scheme.sub_points=4,8,16 --out "$out/mms2d-b"
merge mms-2d-g0.1 "$out/mms2d-a"
merge mms-2d-g0.1-subpoints "$out/mms2d-b"   # one more column (the sub-points swept)
cp "$out/mms2d-a/report.png" "$here/mms-2d-g0.1.png"
fi
# The small-strain amplitude in 2D: every scheme second order (README "The same in 2D at G = 1e-4").
if part mms2d-small; then
report scenes/mms-2d.toml --sweep scheme.method=mpm,ugimp,cpgimp,cpdi1,cpdi2,cpdi-improved,cpdi1-improved,impm,ddmp,tlmpm $m2 --set reference.amplitude=1e-4 --out "$out/mms2d-small-a"
report scenes/mms-2d.toml --sweep scheme.method=ddmp-subpoints $m2 --set reference.amplitude=1e-4 --set scheme.sub_points=4 --out "$out/mms2d-small-b"
merge mms-2d-g1e-4 "$out/mms2d-small-a" "$out/mms2d-small-b"
cp "$out/mms2d-small-a/report.png" "$here/mms-2d-g1e-4.png"
fi
for tube in $(part tubes && echo weak strong); do
  s=scenes/shock-tube-$tube.toml
  report $s --sweep scheme.method=mpm,ugimp,cpgimp,cpdi,cpdi-improved,ddmp $cells --set scheme.sub_points=1 --out "$out/$tube-a"
  report $s --sweep scheme.method=ddmp-subpoints $cells --out "$out/$tube-b"
  report $s --sweep scheme.method=impm,tlmpm $cells --set scheme.sub_points=1 --set scheme.integrator=leapfrog --out "$out/$tube-c"
  merge shock-tube-$tube "$out/$tube-a" "$out/$tube-b" "$out/$tube-c"
  cp "$out/$tube-a/report.png" "$here/shock-tube-$tube.png"
done
# Heat and diffusion (issue 19): every scheme with the leapfrog (impm and tlmpm require it; the
# bodies are at rest, so the integrator does not touch the field: ugimp's Table 6.1 figures are
# bitwise those of the scene's own integrator). Table 6.1's problem at its last time over beta
# = 1 and 0.99 and four resolutions; the convergence problem of B 7.1.2 (the same bar at t =
# 0.25, dt = 5e-6 for every h: below the explicit bound h^2 / 2 at 160 cells); Table 6.2's
# plate over beta = 1 and 0.995 and three resolutions.
if part heat; then
  s1="scheme.method=mpm,ugimp,cpgimp,cpdi,cpdi-improved,impm,ddmp,ddmp-subpoints,tlmpm"
  s2="scheme.method=mpm,ugimp,cpgimp,cpdi1,cpdi2,cpdi-improved,impm,ddmp,ddmp-subpoints,tlmpm"
  lf="--set scheme.integrator=leapfrog"
  report scenes/heat-1d.toml $lf --sweep $s1 --sweep diffusion.flip_fraction=1,0.99 \
    --sweep domain.cells=[10],[20],[40],[80] --out "$out/heat-1d"
  merge heat-1d "$out/heat-1d"
  cp "$out/heat-1d/report.png" "$here/heat-1d.png"
  report scenes/heat-1d.toml $lf --set scheme.end_time=0.25 --set scheme.timestep=5e-6 --sweep $s1 \
    --sweep domain.cells=[10],[20],[40],[80],[160] --out "$out/diffusion-1d"
  merge diffusion-1d-t0.25 "$out/diffusion-1d"
  cp "$out/diffusion-1d/report.png" "$here/diffusion-1d-t0.25.png"
  report scenes/heat-2d.toml $lf --sweep $s2 --sweep diffusion.flip_fraction=1,0.995 \
    --sweep domain.cells=[10,10],[20,20],[40,40] --out "$out/heat-2d"
  merge heat-2d "$out/heat-2d"
  cp "$out/heat-2d/report.png" "$here/heat-2d.png"
fi
