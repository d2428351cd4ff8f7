#!/usr/bin/env python3
"""Cost of the implicit trapezoidal step against the explicit (leapfrog) step on the same 2D grid,
and the crossover step-size ratio above which implicit wins (issue 18, "Measure").

usage: implicit_timing.py [--mscale target/release/mscale[,OTHER,...]] [--cells 50,100] [--repeats 3]
                          [--implicit-cfl 2,8,32] [--explicit-cfl 0.5] [--threads 1] ...

Scene: scenes/mms-2d.toml (Gong's manufactured solution on [0, 1]^2, compressible neo-Hookean,
rollers on every face) at a small amplitude (default 1e-4: strain 3e-4, the elastic regime the
implicit step is meant for), `--set` for the grid, integrator, cfl and end time, no output.
Every configuration of one grid (explicit, then implicit at each cfl) runs once per round and
the rounds repeat, so the runs compared are interleaved; the table quotes medians over rounds.
With several binaries (`--mscale old,new`), each round runs every configuration with each of
them in turn, and one table per binary is printed.

Per step: summary.json `time_breakdown_s.continuum` / `steps` (the whole step, both integrators:
for the implicit one its set-up, Newton, the commit). Per Newton iteration: `implicit.seconds_total`
/ `implicit.newton_iterations`, with its split into residual evaluations, Jacobian assembly and
sparse LU (factorisation and solve). The explicit time step does not change the cost of an explicit
step, so the crossover is r* = (implicit seconds per step) / (explicit seconds per step): an implicit
step of dt_i = r dt_e costs less per simulated second than explicit steps of dt_e when r > r*.
r* is quoted per implicit cfl because the Newton iterations per step grow with the step.
"""
import argparse, json, os, statistics, subprocess, sys, tempfile

ap = argparse.ArgumentParser()
ap.add_argument("--mscale", default="target/release/mscale", help="binary, or several separated by commas")
ap.add_argument("--scene", default="scenes/mms-2d.toml")
ap.add_argument("--cells", default="50,100", help="cells per side (2 x 2 points per cell)")
ap.add_argument("--repeats", type=int, default=3)
ap.add_argument("--explicit-cfl", type=float, default=0.5)
ap.add_argument("--explicit-steps", type=int, default=40)
ap.add_argument("--implicit-cfl", default="2,8,32")
ap.add_argument("--implicit-steps", type=int, default=4)
ap.add_argument("--method", default="cpdi1")
ap.add_argument("--jacobian", default="analytic")
ap.add_argument("--amplitude", type=float, default=1e-4)
ap.add_argument("--threads", default="1", help="RAYON_NUM_THREADS of the runs ('' keeps the default)")
a = ap.parse_args()

# P-wave speed of the scene's material (E = 1e7 Pa, nu = 0.3, rho0 = 1e3): the scene's cfl counts it.
E, NU, RHO = 1e7, 0.3, 1e3
C_P = (E * (1 - NU) / ((1 + NU) * (1 - 2 * NU)) / RHO) ** 0.5


def run(binary, cells, integrator, cfl, steps):
    h = 1.0 / cells
    dt = cfl * h / C_P
    sets = [
        f"domain.cells=[{cells},{cells}]",
        f'scheme.method="{a.method}"',
        f'scheme.integrator="{integrator}"',
        f"scheme.cfl={cfl!r}",
        f"scheme.end_time={steps * dt!r}",
        f"reference.amplitude={a.amplitude!r}",
        "output.snapshots=0",
        "output.particles=false",
        "output.vtk=false",
        "output.plots=false",
    ]
    if integrator == "implicit-trapezoidal":
        sets.append(f'scheme.jacobian="{a.jacobian}"')
    env = dict(os.environ)
    if a.threads:
        env["RAYON_NUM_THREADS"] = a.threads
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "run")
        cmd = [binary, "run", a.scene, "--out", out] + sum((["--set", s] for s in sets), [])
        p = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        with open(os.path.join(out, "summary.json")) as f:
            s = json.load(f)
    if s.get("status") != "completed":
        sys.exit(f"{' '.join(cmd)}: {s.get('error')} {p.stderr[-2000:]}")
    assert s["steps"] == steps, (s["steps"], steps)
    r = {"points": s["points"], "per_step": s["time_breakdown_s"]["continuum"] / s["steps"]}
    im = s.get("implicit")
    if im:
        it = max(im["newton_iterations"], 1)
        r.update(
            its=im["newton_iterations_per_step"],
            per_it=im["seconds_total"] / it,
            res=im["seconds_residual"] / it,
            jac=im["seconds_jacobian"] / it,
            lu=im["seconds_solve"] / it,
            sym=im.get("seconds_symbolic", 0.0) / it,
            unknowns=im["unknowns"],
            symbolic=im.get("symbolic_factorisations", "-"),
        )
    return r


med = statistics.median
cfls = [float(c) for c in a.implicit_cfl.split(",")]
binaries = a.mscale.split(",")
for cells in [int(c) for c in a.cells.split(",")]:
    rounds = {b: [] for b in binaries}
    for _ in range(a.repeats):
        for b in binaries:
            row = [run(b, cells, "leapfrog", a.explicit_cfl, a.explicit_steps)]
            row += [run(b, cells, "implicit-trapezoidal", c, a.implicit_steps) for c in cfls]
            rounds[b].append(row)
    for b in binaries:
        print(f"# {a.scene}, method {a.method}, amplitude {a.amplitude}, jacobian {a.jacobian}, "
              f"RAYON_NUM_THREADS={a.threads or 'default'}, {a.repeats} interleaved rounds, medians; {b}")
        print("| cells | points | unknowns | integrator, cfl | steps | ms/step | Newton it/step | ms/iteration "
              "(residual / Jacobian / LU, of it symbolic) | symbolic LUs | r* = t_imp / t_exp | step ratio r = cfl / explicit cfl |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        ex = med(r[0]["per_step"] for r in rounds[b])
        pts = rounds[b][0][0]["points"]
        print(f"| {cells}x{cells} | {pts} | | leapfrog, {a.explicit_cfl} | {a.explicit_steps} | {1e3 * ex:.3f} | | | | | |")
        for k, c in enumerate(cfls, start=1):
            col = [r[k] for r in rounds[b]]
            m = {key: med(x[key] for x in col) for key in ("per_step", "its", "per_it", "res", "jac", "lu", "sym")}
            print(
                f"| {cells}x{cells} | {pts} | {col[0]['unknowns']} | implicit, {c:g} | {a.implicit_steps} | {1e3 * m['per_step']:.1f} | "
                f"{m['its']:.2f} | {1e3 * m['per_it']:.1f} ({1e3 * m['res']:.1f} / {1e3 * m['jac']:.1f} / {1e3 * m['lu']:.1f}, {1e3 * m['sym']:.1f}) | "
                f"{col[0]['symbolic']} | {m['per_step'] / ex:.0f} | {c / a.explicit_cfl:g} |"
            )
        sys.stdout.flush()
