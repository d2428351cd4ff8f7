#!/usr/bin/env python3
"""Error of a coupled (or continuum) 1D bar run against direct MD, by the seed's eq. 7.12:
eps = sqrt(sum (s_MD - s_MS)^2 / sum s_MD^2), sigma_xx over material points, in the reference
(Lagrangian) coordinate, at the snapshot times of the run.

usage: compare_direct.py RUN_DIR DIRECT_CSV --strain -0.05 --interface-nm 51.11 [--times 5,10]

`mscale report error-vs-time SCENE --reference DIRECT_CSV --reference-times 5,10 ...` computes the
same numbers in Rust for every run of a sweep (reference coordinate taken from the scene's
bodies); this script scores one existing run directory.

RUN_DIR: an `mscale run` directory (snapshots/index.csv, particles_*.csv).
DIRECT_CSV: `md-worker direct` output (time_ps,slab_center_nm,sxx_gpa,...; reference x).
The run's initial positions x0 (strained configuration) are mapped to the reference
coordinate: X = x0 / (1 + strain) left of the interface, X = interface/(1 + strain) + (x0 - interface)
right of it. Direct-MD slabs are interpolated linearly in X.
"""
import argparse, csv, math, os, sys

ap = argparse.ArgumentParser()
ap.add_argument("run")
ap.add_argument("direct")
ap.add_argument("--strain", type=float, required=True)
ap.add_argument("--interface-nm", type=float, required=True)
ap.add_argument("--times", default="5,10", help="ps")
ap.add_argument("--wall-nm", type=float, default=1.0, help="skip points this close to the bar's ends (frozen MD layers)")
a = ap.parse_args()

direct = {}
with open(a.direct) as f:
    for r in csv.DictReader(f):
        direct.setdefault(round(float(r["time_ps"]), 6), []).append((float(r["slab_center_nm"]), float(r["sxx_gpa"])))
for v in direct.values():
    v.sort()

def interp(rows, x):
    if x <= rows[0][0]:
        return rows[0][1]
    for (x0, y0), (x1, y1) in zip(rows, rows[1:]):
        if x0 <= x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return rows[-1][1]

index = list(csv.DictReader(open(os.path.join(a.run, "snapshots", "index.csv"))))
out = []
for t in [float(s) for s in a.times.split(",")]:
    snap = min(index, key=lambda r: abs(float(r["time"]) * 1e12 - t))
    ts = float(snap["time"]) * 1e12
    key = min(direct, key=lambda k: abs(k - ts))
    if abs(key - ts) > 1e-3:
        sys.exit(f"no direct-MD rows at t = {ts} ps (nearest {key})")
    rows = direct[key]
    xmax = rows[-1][0] + 0.5 * (rows[-1][0] - rows[-2][0])
    num = den = 0.0
    n = 0
    for r in csv.DictReader(open(os.path.join(a.run, "snapshots", snap["file"]))):
        x0 = float(r["x0"]) * 1e9
        X = x0 / (1 + a.strain) if x0 < a.interface_nm else a.interface_nm / (1 + a.strain) + (x0 - a.interface_nm)
        if X < a.wall_nm or X > xmax - a.wall_nm:
            continue
        s_ms = float(r["sxx"]) / 1e9
        s_md = interp(rows, X)
        num += (s_md - s_ms) ** 2
        den += s_md ** 2
        n += 1
    eps = math.sqrt(num / den)
    out.append((ts, eps, n))
    print(f"t = {ts:.2f} ps: eq. 7.12 error of sigma_xx = {100 * eps:.2f} % over {n} points")
