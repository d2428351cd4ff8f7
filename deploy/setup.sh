#!/usr/bin/env bash
# Installs what mscale needs beyond cargo for its optional features. The default build needs
# none of it. Usage:
#   bash deploy/setup.sh            # nothing to install for the default build; prints what is optional
#   bash deploy/setup.sh nvrtc      # NVRTC from PyPI (cargo feature `cuda`: kernels compile in CI without a GPU)
#   bash deploy/setup.sh lammps     # LAMMPS, to regenerate the MD golden data (tests do not need it)
#   bash deploy/setup.sh mpi        # Open MPI and libclang (cargo feature `mpi` of md-worker: rsmpi's bindgen)
#   bash deploy/setup.sh browser    # headless Chromium, for the dashboard's browser test (MSCALE_REQUIRE_BROWSER=1)
#   bash deploy/setup.sh python     # a virtual environment (MSCALE_VENV, default target/py-venv) with ./python[test]
#   bash deploy/setup.sh all
# Prints, for nvrtc, the export line that puts libnvrtc on LD_LIBRARY_PATH.
set -euo pipefail

need_apt() {
  local missing=()
  for p in "$@"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
  if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing ${missing[*]}" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
}

nvrtc_dir() {
  python3 - <<'PY'
import importlib.util, os, sys
spec = importlib.util.find_spec("nvidia.cuda_nvrtc")
if spec is None or not spec.submodule_search_locations:
    sys.exit(1)
print(os.path.join(list(spec.submodule_search_locations)[0], "lib"))
PY
}

want="${1:-none}"
case "$want" in
  none)
    echo "setup: the default build needs only cargo; optional: nvrtc, lammps, mpi, browser, python, all" ;;
  all|nvrtc|lammps|mpi|browser|python) ;;
  *) echo "setup: unknown component '$want' (expected nvrtc, lammps, mpi, browser, python or all)" >&2; exit 2 ;;
esac
if [ "$want" = lammps ] || [ "$want" = all ]; then
  need_apt lammps lammps-data
fi
if [ "$want" = mpi ] || [ "$want" = all ]; then
  # mpicc and the headers for the `mpi` crate's build (bindgen needs libclang), mpirun to run.
  need_apt libopenmpi-dev openmpi-bin libclang-dev
fi
if [ "$want" = browser ] || [ "$want" = all ]; then
  # Debian's chromium: `chromium --headless` loads the dashboard in orchestrator/tests/dashboard.rs.
  need_apt chromium fonts-dejavu-core
fi
if [ "$want" = python ] || [ "$want" = all ]; then
  # The Python client and loaders (python/): gRPC stubs are generated from proto/ at install.
  venv="${MSCALE_VENV:-$(cd "$(dirname "$0")/.." && pwd)/target/py-venv}"
  python3 -m venv --help >/dev/null 2>&1 || need_apt python3-venv
  [ -x "$venv/bin/python" ] || python3 -m venv "$venv"
  "$venv/bin/python" -m pip install -q --upgrade pip >&2
  "$venv/bin/python" -m pip install -q "$(cd "$(dirname "$0")/.." && pwd)/python[test]" >&2
  echo "setup: python package installed into $venv (run: $venv/bin/python -m pytest python/tests)" >&2
fi
if [ "$want" = nvrtc ] || [ "$want" = all ]; then
  if ! nvrtc_dir >/dev/null 2>&1; then
    echo "setup: installing nvidia-cuda-nvrtc-cu12 from PyPI" >&2
    python3 -m pip install -q nvidia-cuda-nvrtc-cu12 >&2
  fi
  echo "export LD_LIBRARY_PATH=$(nvrtc_dir)\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
fi
