#!/usr/bin/env python3
"""Split a coupled snapshot's eq. (7.12) error of sigma_yy into rows of the direct MD's bins.

Usage: python3 tests/golden/cu-notch-jet-2d-half/rows.py RUN/snapshots/particles_N.csv TIME_PS
Prints the error over the scored particles (those in bins holding at least 400 atoms, as the
scene's score takes them; it reproduces `mscale report score` to the digit), then per row of bins:
the particle count, the particles' mean sigma_yy, the bins' mean at the same particles (GPa) and
the row's share of the squared error.
"""
import collections, csv, math, pathlib, sys

snap, t = sys.argv[1], float(sys.argv[2])
ref = pathlib.Path(__file__).with_name("direct-jet.csv")
w = 1.8075  # bin width (nm)
bins = {}
for r in csv.reader(l for l in open(ref) if not l.startswith("#")):
    if r[0] == "time_ps" or abs(float(r[0]) - t) > 1e-6:
        continue
    bins[(int(float(r[1]) // w), int(float(r[2]) // w))] = (int(r[3]), float(r[7]))
rows = collections.defaultdict(lambda: [0, 0.0, 0.0, 0.0])
num = den = 0.0
n = 0
for p in csv.DictReader(open(snap)):
    k = (int(float(p["x"]) * 1e9 // w), int(float(p["y"]) * 1e9 // w))
    if k not in bins or bins[k][0] < 400:
        continue
    s, sr = float(p["syy"]) / 1e9, bins[k][1]
    num += (s - sr) ** 2
    den += sr**2
    n += 1
    r = rows[k[1]]
    r[0] += 1
    r[1] += s
    r[2] += sr
    r[3] += (s - sr) ** 2
print(f"error {100 * math.sqrt(num / den):.2f} % over {n} particles")
for ky in sorted(rows):
    c, s, sr, e2 = rows[ky]
    print(f"y {ky * w:6.1f}-{(ky + 1) * w:5.1f} nm  n {c:4d}  coupled {s / c:8.1f}  direct {sr / c:8.1f}  share {100 * e2 / num:5.1f} %")
