#!/usr/bin/env bash
# Regenerate md-worker's LAMMPS golden data (tests do not need LAMMPS; they read the committed files).
# Needs: lmp (Debian: apt-get install -y lammps lammps-data) and python3 (standard library only).
set -euo pipefail
cd "$(dirname "$0")/../.."
command -v lmp >/dev/null || { echo "lmp not found: apt-get install -y lammps lammps-data" >&2; exit 1; }
python3 md-worker/scripts/make_golden.py
