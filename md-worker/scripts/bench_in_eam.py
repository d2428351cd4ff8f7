#!/usr/bin/env python3
"""LAMMPS bench/in.eam (32,000 Cu_u3 atoms, md-worker/scripts/lammps_in.eam) against md-worker bench
on the same 20x20x20-cell Cu_u3 box (one box; md-worker's bench runs 300 K, 1 fs, L_xx = 1e-3/ps,
in.eam 1600 K, 5 fs: LAMMPS rebuilds its list more often), interleaved run by run. Prints wall
and CPU ns/atom-step (CPU: user + sys of the whole process over its atom-steps).
Usage: python3 md-worker/scripts/bench_in_eam.py [RUNS]   (from the repository root, after
cargo build --release -p md-worker; MD=path/to/md-worker runs another binary)"""
import json, os, re, resource, statistics as st, subprocess, sys

runs = int(sys.argv[1]) if len(sys.argv) > 1 else 5
REPS, STEPS, N = 5, 20, 32000
LMP = ["lmp", "-sf", "opt", "-in", "md-worker/scripts/lammps_in.eam", "-log", "none"]
MD = [os.environ.get("MD", "target/release/md-worker"), "bench", "--potential", "md-worker/potentials/Cu_u3.eam", "--lattice", "fcc", "--a0", "3.615",
      "--cells", "20", "--boxes", "1", "--steps", str(STEPS), "--reps", str(REPS), "--threads", "1", "--backend", "cpu"]


def timed(cmd, env=None):
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env).stdout
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return out, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


print("commands:\n  " + " ".join(LMP) + "\n  MSCALE_MD_SIMD=scalar|auto " + " ".join(MD))
print("load before:", open("/proc/loadavg").read().strip())
rows = []
for r in range(runs):
    out, c = timed(LMP)
    lw = float(re.search(r"Loop time of ([0-9.eE+-]+)", out).group(1))
    row = [lw / (N * 100) * 1e9, c / (N * 100) * 1e9]
    for p in ["scalar", "auto"]:
        out, c = timed(MD, dict(os.environ, MSCALE_MD_SIMD=p))
        d = json.loads(out)
        row += [d["ns_per_atom_step"], c / (REPS * N * STEPS) * 1e9]
    rows.append(row)
    print(f"run {r + 1} (wall / cpu ns/atom-step): LAMMPS {row[0]:.0f} / {row[1]:.0f} | scalar {row[2]:.0f} / {row[3]:.0f} | auto ({d['simd']}) {row[4]:.0f} / {row[5]:.0f}")
print("load after:", open("/proc/loadavg").read().strip())
m = [st.median(x[k] for x in rows) for k in range(6)]
print(f"median of {runs}: LAMMPS {m[0]:.0f} / {m[1]:.0f}; md-worker scalar {m[2]:.0f} / {m[3]:.0f} ({m[0]/m[2]:.2f}x wall, {m[1]/m[3]:.2f}x cpu); "
      f"default path {m[4]:.0f} / {m[5]:.0f} ({m[0]/m[4]:.2f}x wall, {m[1]/m[5]:.2f}x cpu)")
