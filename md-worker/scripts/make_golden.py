#!/usr/bin/env python3
"""Make LAMMPS data files and golden reference values for md-worker's tests.

Usage: python3 md-worker/scripts/make_golden.py   (called by make_golden.sh; needs `lmp`)
Writes md-worker/tests/golden/*.data (inputs) and *.golden (LAMMPS output, %.17g).
"""
import math, os, random, subprocess, sys, tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
CRATE = os.path.dirname(HERE)
GOLD = os.path.join(CRATE, "tests", "golden")
POT = os.path.join(CRATE, "potentials")
REGEN = "bash md-worker/scripts/make_golden.sh"
MVV2E = 1.0364269e-4
KB = 8.617343e-5

def fcc(cells, a):
    basis = [(0, 0, 0), (0.5, 0.5, 0), (0.5, 0, 0.5), (0, 0.5, 0.5)]
    out = []
    for i in range(cells):
        for j in range(cells):
            for k in range(cells):
                for b in basis:
                    out.append([(i + b[0]) * a, (j + b[1]) * a, (k + b[2]) * a])
    return out

def make_config(name, cells, a, strain, jitter, temp, seed, mass=63.546):
    rng = random.Random(seed)
    pos = fcc(cells, a)
    L = [cells * a * (1.0 + s) for s in strain]
    for p in pos:
        for d in range(3):
            p[d] = p[d] * (1.0 + strain[d]) + rng.uniform(-jitter, jitter)
            p[d] %= L[d]
    sig = math.sqrt(KB * temp / (mass * MVV2E))
    vel = [[rng.gauss(0.0, sig) for _ in range(3)] for _ in pos]
    n = len(pos)
    mean = [sum(v[d] for v in vel) / n for d in range(3)]
    for v in vel:
        for d in range(3):
            v[d] -= mean[d]
    path = os.path.join(GOLD, name + ".data")
    with open(path, "w") as f:
        f.write("LAMMPS data file for md-worker golden tests (%s); regenerate: %s\n\n" % (name, REGEN))
        f.write("%d atoms\n1 atom types\n\n" % n)
        for d, ax in enumerate("xyz"):
            f.write("0.0 %.17g %slo %shi\n" % (L[d], ax, ax))
        f.write("\nMasses\n\n1 %.17g\n\nAtoms # atomic\n\n" % mass)
        for i, p in enumerate(pos):
            f.write("%d 1 %.17g %.17g %.17g\n" % (i + 1, p[0], p[1], p[2]))
        f.write("\nVelocities\n\n")
        for i, v in enumerate(vel):
            f.write("%d %.17g %.17g %.17g\n" % (i + 1, v[0], v[1], v[2]))
    return path

POTS = {
    "mishin": ("eam/alloy", "Cu_mishin1.eam.alloy", "* * {f} Cu"),
    "u3": ("eam", "Cu_u3.eam", "1 1 {f}"),
}

def run_lammps(case, pot, data, steps, thermo_every, deform):
    style, fname, coeff = POTS[pot]
    potfile = os.path.join(POT, fname)
    with tempfile.TemporaryDirectory() as tmp:
        inp = os.path.join(tmp, "in.lmp")
        dump = os.path.join(tmp, "dump.out")
        lines = [
            "units metal", "atom_style atomic", "boundary p p p",
            "read_data %s" % data,
            "pair_style %s" % style,
            "pair_coeff " + coeff.format(f=potfile),
            "neighbor 1.0 bin", "neigh_modify every 1 delay 0 check yes",
            "timestep 0.001", "fix 1 all nve",
        ]
        if deform:
            lines.append("fix 2 all deform 1 " + deform + " remap x")
        lines += [
            "thermo_style custom step pe ke pxx pyy pzz pxy pxz pyz lx ly lz",
            "thermo_modify format float %.17g norm no",
            "thermo %d" % thermo_every,
            "dump d all custom %d %s id type x y z vx vy vz fx fy fz" % (max(steps, 1), dump),
            "dump_modify d format float %.17g sort id",
            "run %d" % steps,
        ]
        open(inp, "w").write("\n".join(lines) + "\n")
        res = subprocess.run(["lmp", "-in", inp, "-log", os.path.join(tmp, "log.lammps"), "-screen", "none"],
                             cwd=tmp, capture_output=True, text=True)
        if res.returncode != 0:
            sys.exit("lammps failed for %s: %s %s" % (case, res.stdout, res.stderr))
        log = open(os.path.join(tmp, "log.lammps")).read().splitlines()
        thermo = []
        on = False
        for ln in log:
            if ln.strip().startswith("Step"):
                on = True
                continue
            if on:
                if ln.startswith("Loop time"):
                    break
                thermo.append(ln.split())
        snaps = open(dump).read().split("ITEM: TIMESTEP")
        last = snaps[-1].strip().splitlines()
        ai = last.index("ITEM: ATOMS id type x y z vx vy vz fx fy fz")
        atoms = last[ai + 1:]
        version = subprocess.run(["lmp", "-h"], capture_output=True, text=True).stdout.strip().splitlines()[0]
    out = os.path.join(GOLD, case + ".golden")
    with open(out, "w") as f:
        f.write("# regenerate: %s\n" % REGEN)
        f.write("# produced by: %s\n" % version.strip())
        f.write("# lammps input:\n")
        for ln in lines:
            f.write("#   %s\n" % ln.replace(POT, "md-worker/potentials").replace(GOLD, "md-worker/tests/golden"))
        f.write("potential %s\nstyle %s\ndata %s\nsteps %d\ndt 0.001\n" % (fname, style, os.path.basename(data), steps))
        f.write("deform %s\n" % (deform if deform else "none"))
        f.write("thermo_columns step pe ke pxx pyy pzz pxy pxz pyz lx ly lz\n")
        for t in thermo:
            f.write("thermo " + " ".join(t) + "\n")
        f.write("atom_columns id type x y z vx vy vz fx fy fz\n")
        for a in atoms:
            f.write("atom " + a.strip() + "\n")
    print("wrote", out)

def main():
    os.makedirs(GOLD, exist_ok=True)
    d108 = make_config("cu108_hot", 3, 3.6, (0.0, 0.0, 0.0), 0.08, 600.0, 1)
    d256s = make_config("cu256_strained", 4, 3.615, (0.012, -0.004, 0.0), 0.05, 300.0, 2)
    d256h = make_config("cu256_hot", 4, 3.63, (0.0, 0.0, 0.0), 0.15, 1500.0, 3)
    for pot in POTS:
        for d in (d108, d256s, d256h):
            name = os.path.basename(d)[:-5]
            run_lammps("eval_%s_%s" % (pot, name), pot, d, 0, 1, None)
        run_lammps("nve_%s_cu108_hot" % pot, pot, d108, 300, 50, None)
        run_lammps("affine_%s_cu256_strained" % pot, pot, d256s, 300, 50, "x trate 0.05 y trate -0.02")

if __name__ == "__main__":
    main()
