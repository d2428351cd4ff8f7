"""The README's error-against-cost figure from Python: log10 pressure L1 error (of the jump)
against log10 wall seconds, one series per method, as `mscale report error-vs-time` draws it.

Runs the sweep through a running `mscale serve` (every combination one job, watched to its end
and fetched), or reads an existing report.csv with --report:

    python python/examples/error_vs_cost.py --server 127.0.0.1:50100 --token-file state/token \\
        --scene scenes/shock-tube-weak.toml --sweep scheme.method=ugimp,cpdi \\
        --sweep scheme.particles_per_cell=8,16 --set scheme.sub_points=1 --out sweep --png error-vs-cost.png
    python python/examples/error_vs_cost.py --report runs/shock-tube-weak-report/report.csv --png fig.png
"""

import argparse
import sys

import numpy as np

import mscale


def value(v: str):
    for t in (int, float):
        try:
            return t(v)
        except ValueError:
            pass
    return v


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server", default="127.0.0.1:50100")
    ap.add_argument("--token-file")
    ap.add_argument("--ca-file")
    ap.add_argument("--scene")
    ap.add_argument("--sweep", action="append", default=[], help="KEY=V1,V2,... (repeatable)")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE applied to every run")
    ap.add_argument("--report", help="plot this report.csv instead of running a sweep")
    ap.add_argument("--out", default="sweep", help="where the sweep's runs and report.csv go")
    ap.add_argument("--error", default="pressure_l1", help="the error column to plot")
    ap.add_argument("--png", default="error-vs-cost.png")
    a = ap.parse_args()
    if a.report:
        frame = mscale.load_report(a.report)
    else:
        if not a.scene or not a.sweep:
            ap.error("--scene and at least one --sweep are needed (or --report)")
        sweeps = {}
        for s in a.sweep:
            key, _, values = s.partition("=")
            sweeps[key] = [value(v) for v in values.split(",")]
        with mscale.Client(a.server, token_file=a.token_file, ca_file=a.ca_file) as c:
            frame = mscale.sweep(c, a.scene, sweeps, sets=a.set, out=a.out)
    done = frame[(frame["status"] == "completed") & frame[a.error].notna() & (frame[a.error] > 0)]
    if done.empty:
        print(f"no completed run has a positive {a.error}", file=sys.stderr)
        return 1
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for method, g in done.groupby("method"):
        g = g.sort_values("wall_seconds")
        ax.plot(np.log10(g["wall_seconds"]), np.log10(g[a.error]), "o-", label=method)
    ax.set_xlabel("log10 wall time (s)")
    ax.set_ylabel(f"log10 {a.error}")
    ax.set_title("error against cost")
    ax.legend()
    fig.tight_layout()
    fig.savefig(a.png, dpi=100)
    print(done[["method", "wall_seconds", a.error]].to_string(index=False))
    print(f"figure in {a.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
