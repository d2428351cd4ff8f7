#!/usr/bin/env bash
# Seeds of an AFL target when fuzz/corpus/TARGET is empty: bash fuzz/seeds.sh TARGET DIR.
# scene: the mutation corpus orchestrator/tests/fuzz-corpus/scene and the shipped scenes;
# users: orchestrator/tests/fuzz-corpus/users; step: md-worker/tests/fuzz-corpus/worker-messages
# (its first byte numbers the method as the target does); eam: small potentials of the three
# formats (the tables of md-worker/tests/fuzz_inputs.rs) and Cu_u3.eam, each after its format
# byte; lammps: md-worker's golden data files and a small one with every section; checkpoint:
# the checkpoints of `mscale run --checkpoint-every 1` of the target's three scenes (needs
# target/debug/mscale or MSCALE_BIN), each after its scene byte.
set -euo pipefail
cd "$(dirname "$0")/.."
target=${1:?usage: fuzz/seeds.sh TARGET DIR}
dir=${2:?usage: fuzz/seeds.sh TARGET DIR}
rm -rf "$dir"
mkdir -p "$dir"
small() { find "$@" -maxdepth 1 -type f -size -64k; }
case "$target" in
  scene) for f in $(small orchestrator/tests/fuzz-corpus/scene scenes tests/data); do case "$f" in *.md) ;; *) cp "$f" "$dir/$(basename "$f")" ;; esac; done ;;
  users) cp orchestrator/tests/fuzz-corpus/users/* "$dir/" ;;
  step) cp md-worker/tests/fuzz-corpus/worker-messages/* "$dir/" ;;
  eam)
    python3 - "$dir" <<'PY'
import math, sys
d = sys.argv[1]
nrho, nr, drho, dr, cut = 20, 40, 0.05, 0.15, 5.0
f = [-math.sqrt(k * drho) for k in range(nrho)]
rho = [math.exp(-3 * (k * dr / 2.55 - 1)) * (1 - k * dr / cut) ** 2 if k * dr < cut else 0.0 for k in range(nr)]
rphi = [k * dr * 0.5 * math.exp(-6 * (k * dr / 2.55 - 1)) * (1 - k * dr / cut) ** 2 if k * dr < cut else 0.0 for k in range(nr)]
block = lambda v: "\n".join(" ".join(f"{x:.10e}" for x in v[i:i + 5]) for i in range(0, len(v), 5)) + "\n"
z = [math.sqrt(max(v, 0.0) / (27.2 * 0.529)) for v in rphi]
grid = f"{nrho} {drho} {nr} {dr} {cut}\n"
funcfl = f"small funcfl\n29 63.55 3.615 FCC\n{grid}" + block(f) + block(z) + block(rho)
el = lambda name, dens: f"29 63.55 3.615 FCC {name}\n" + block(f) + block(rho) * dens
setfl = "c1\nc2\nc3\n2 Cu Cv\n" + grid + el("Cu", 1) + el("Cv", 1) + block(rphi) * 3
fs = "c1\nc2\nc3\n2 Cu Cv\n" + grid + el("Cu", 2) + el("Cv", 2) + block(rphi) * 3
for k, (name, text) in enumerate([("funcfl", funcfl), ("setfl", setfl), ("fs", fs)]):
    open(f"{d}/small-{name}", "wb").write(bytes([k]) + text.encode())
PY
    { printf '\000'; cat md-worker/potentials/Cu_u3.eam; } > "$dir/Cu_u3" ;;
  lammps)
    cp md-worker/tests/golden/cu108_hot.data "$dir/"
    printf 'small\n\n4 atoms\n2 atom types\n\n0 3.615 xlo xhi\n0 3.615 ylo yhi\n-1 2.615 zlo zhi\n\nMasses\n\n1 63.55\n2 63.55\n\nAtoms # atomic\n\n1 1 0 0 -1\n2 1 1.8075 1.8075 -1 0 0 0\n3 1 1.8075 0 0.8075 1 -1 0\n4 1 0 1.8075 0.8075\n\nVelocities\n\n1 1 0 0\n2 0 1 0\n3 0 0 1\n4 -1 -1 -1\n' > "$dir/small.data" ;;
  checkpoint)
    mscale=${MSCALE_BIN:-target/debug/mscale}
    [ -x "$mscale" ] || { echo "seeds.sh: $mscale is missing: cargo build -p orchestrator --bin mscale (or set MSCALE_BIN)" >&2; exit 2; }
    u3=$PWD/md-worker/potentials/Cu_u3.eam
    work=$(mktemp -d)
    trap 'rm -rf "$work"' EXIT
    run() { RUST_LOG=warn "$mscale" run "$@" --checkpoint-every 1 >/dev/null 2>&1; }
    run tests/data/small.toml --set scheme.end_time=0.05 --set 'domain.cells=[20]' --out "$work/0"
    run tests/data/md-small.toml --set "bodies.left.material.potential=\"$u3\"" --set "bodies.right.material.potential=\"$u3\"" --out "$work/1"
    run scenes/pnp-debye.toml --out "$work/2"
    for k in 0 1 2; do
      first=$(ls "$work/$k/checkpoints/"*.ckpt | head -n 1)
      # The body alone (the target makes the header match) and the whole file (top bit set).
      { printf "\\00$k"; tail -n +2 "$first"; } > "$dir/scene$k-body"
      { printf "\\20$k"; cat "$first"; } > "$dir/scene$k-file"
    done ;;
  *) echo "seeds.sh: unknown target '$target'" >&2; exit 2 ;;
esac
echo "seeds.sh: $(ls "$dir" | wc -l) seeds of $target in $dir" >&2
