#!/usr/bin/env python3
"""The vibrating bar study of issue 17 (notes A.9 T5): errors over time, every 2,000 steps.

Runs scenes/vibrating-bar-1d.toml once per configuration with `output.snapshots = 10` and
scores every snapshot (x0, x, vx, sxx of each point) against the exact solution with the
measure of summary.json `errors` (sqrt(sum_p V0_p |q_p - q(X_p, t)|^2), V0_p = m_p / rho0).
The last snapshot's score is checked against the run's own summary.json (to 1e-9 relative).

    python3 scripts/vibrating_bar_study.py [--mscale target/debug/mscale] [--amplitude 3e-3]
        [--only NAME,...] [--out DIR]

Prints a markdown table (displacement L2 per 2,000 steps, then velocity and stress at the
end) for continuum/docs/nullspace-filters.md.
"""

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import time

CONFIGS = [
    ("mpm", []),
    ("mpm + local", ['scheme.nullspace_filter="local"']),
    ("mpm + global-svd", ['scheme.nullspace_filter="global-svd"']),
    ("linear", ['scheme.gradient_correction="linear"']),
    ("linear + local", ['scheme.gradient_correction="linear"', 'scheme.nullspace_filter="local"']),
    ("linear + global-svd", ['scheme.gradient_correction="linear"', 'scheme.nullspace_filter="global-svd"']),
    ("ddmp", ['scheme.method="ddmp"']),
]

RHO0, MODULUS = 1.0, 1e3


def exact(a, x0, t):
    c = math.sqrt(MODULUS / RHO0)
    u = a * math.sin(2 * math.pi * x0) * math.sin(c * math.pi * t)
    v = a * c * math.pi * math.sin(2 * math.pi * x0) * math.cos(c * math.pi * t)
    s = MODULUS * 2 * math.pi * a * math.cos(2 * math.pi * x0) * math.sin(c * math.pi * t)
    return u, v, s


def score(path, a, t):
    eu = ev = es = 0.0
    with open(path) as f:
        for r in csv.DictReader(f):
            x0, x, vx, sxx, v0 = float(r["x0"]), float(r["x"]), float(r["vx"]), float(r["sxx"]), float(r["mass"]) / RHO0
            u, v, s = exact(a, x0, t)
            eu += v0 * (x - x0 - u) ** 2
            ev += v0 * (vx - v) ** 2
            es += v0 * (sxx - s) ** 2
    return math.sqrt(eu), math.sqrt(ev), math.sqrt(es)


def run(mscale, name, sets, a, out):
    d = os.path.join(out, name.replace(" ", "").replace("+", "_"))
    cmd = [mscale, "run", "scenes/vibrating-bar-1d.toml", "--out", d, "--set", "output.snapshots=10", "--set", f"reference.amplitude={a}"]
    for s in sets:
        cmd += ["--set", s]
    t0 = time.time()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.time() - t0
    rows = []
    with open(os.path.join(d, "snapshots", "index.csv")) as f:
        for r in csv.DictReader(f):
            step, t = int(r["step"]), float(r["time"])
            if step > 0:
                rows.append((step, score(os.path.join(d, "snapshots", r["file"]), a, t)))
    summary = json.load(open(os.path.join(d, "summary.json")))
    e = summary.get("errors") or {}
    if p.returncode == 0:
        last = rows[-1][1]
        for k, q in enumerate(["displacement_l2", "velocity_l2", "stress_l2"]):
            if abs(last[k] - e[q]) > 1e-9 * abs(e[q]):
                sys.exit(f"{name}: snapshot score {last[k]} disagrees with summary.json {q} = {e[q]}")
    return rows, wall, p.returncode, (p.stderr.strip().splitlines() or [""])[-1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--mscale", default="target/debug/mscale")
    ap.add_argument("--amplitude", type=float, default=3e-3)
    ap.add_argument("--only", default="")
    ap.add_argument("--out", default="")
    args = ap.parse_args()
    out = args.out or tempfile.mkdtemp(prefix="vbar-")
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    results = []
    for name, sets in CONFIGS:
        if only and name not in only:
            continue
        rows, wall, rc, last = run(args.mscale, name, sets, args.amplitude, out)
        results.append((name, rows, wall, rc, last))
        print(f"{name}: {wall:.1f} s, rc {rc}" + ("" if rc == 0 else f": {last}"), file=sys.stderr, flush=True)
    steps = sorted({s for _, rows, _, _, _ in results for s, _ in rows})
    print(f"A = {args.amplitude:g}: displacement L2 (m) after N steps")
    print()
    print("| configuration | " + " | ".join(str(s) for s in steps) + " | velocity L2 end | stress L2 end | wall (s) |")
    print("|---|" + "---|" * (len(steps) + 3))
    for name, rows, wall, rc, _ in results:
        by = dict(rows)
        cells = [f"{by[s][0]:.3g}" if s in by else "stopped" for s in steps]
        end = rows[-1][1] if rows and rc == 0 else (math.nan, math.nan, math.nan)
        print(f"| {name} | " + " | ".join(cells) + f" | {end[1]:.3g} | {end[2]:.3g} | {wall:.1f} |")


if __name__ == "__main__":
    main()
