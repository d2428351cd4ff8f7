#!/usr/bin/env bash
# Installs what mscale needs beyond cargo for its optional features. The default build needs
# none of it. Usage:
#   bash deploy/setup.sh            # nothing to install for the default build; prints what is optional
#   bash deploy/setup.sh nvrtc      # NVRTC from PyPI (cargo feature `cuda`: kernels compile in CI without a GPU)
#   bash deploy/setup.sh lammps     # LAMMPS, to regenerate the MD golden data (tests do not need it)
#   bash deploy/setup.sh mpi        # Open MPI and libclang (cargo feature `mpi` of md-worker: rsmpi's bindgen)
#   bash deploy/setup.sh browser    # headless Chromium, for the dashboard's browser test (MSCALE_REQUIRE_BROWSER=1)
#   bash deploy/setup.sh python     # a virtual environment (MSCALE_VENV, default target/py-venv) with ./python[test]
#   bash deploy/setup.sh slurm      # a single-node Slurm cluster on this machine, started (see slurm_start below)
#   bash deploy/setup.sh slurm-stop # stops that cluster's daemons (its state directory is kept)
#   bash deploy/setup.sh all        # every component above but the Slurm cluster (started only when asked for)
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

# ------------------------------------------------------------------ a single-node Slurm cluster
# Debian's slurm-wlm and munge: munged, then slurmctld and slurmd as root with
# ProctrackType=proctrack/linuxproc, TaskPlugin=task/none and SelectType=select/cons_tres (no
# cgroups needed, so it runs in a container). The node's name is `hostname -s` (at 127.0.0.1),
# its CPUs, sockets, cores and memory those `slurmd -C` finds. State, spool, logs and pid files
# live under MSCALE_SLURM_DIR (default ${TMPDIR:-/tmp}/mscale-slurm); the configuration is
# /etc/slurm/slurm.conf, where Slurm's commands look for it, written only when it is absent or
# one this script wrote (a site's own configuration is never replaced). Idempotent: daemons
# that run are left running, and it returns once `sinfo` shows the node idle (or mixed/allocated
# when jobs already run on it). No accounting database: jobs are followed with squeue and
# `scontrol show job` (finished jobs stay visible for MinJobAge = 600 s).
SLURM_DIR="${MSCALE_SLURM_DIR:-${TMPDIR:-/tmp}/mscale-slurm}"
SLURM_CONF=/etc/slurm/slurm.conf
SLURM_MARK="# Written by mscale deploy/setup.sh slurm"

running() { [ -s "$1" ] && kill -0 "$(cat "$1")" 2>/dev/null; }

slurm_start() {
  need_apt slurm-wlm munge
  local node conf hw
  node=$(hostname -s)
  mkdir -p "$SLURM_DIR"/{state,spool,log}
  # munge: a key if there is none (the package's postinst usually made one), then munged.
  if [ ! -s /etc/munge/munge.key ]; then
    echo "setup: creating the munge key /etc/munge/munge.key" >&2
    mkdir -p /etc/munge
    mungekey --create --keyfile=/etc/munge/munge.key
  fi
  chown munge:munge /etc/munge /etc/munge/munge.key
  chmod 0700 /etc/munge
  chmod 0600 /etc/munge/munge.key
  mkdir -p /run/munge /var/lib/munge /var/log/munge
  chown munge:munge /run/munge /var/lib/munge /var/log/munge
  if ! munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
    runuser -u munge -- /usr/sbin/munged
    for _ in $(seq 50); do munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.2; done
    munge -n | unmunge >/dev/null || { echo "setup: munged does not answer (see /var/log/munge/munged.log)" >&2; exit 1; }
  fi
  # The configuration, from this machine.
  hw=$(slurmd -C | head -n 1 | sed -e 's/^NodeName=[^ ]* //' -e 's/ UpTime=.*//')
  if [ -e "$SLURM_CONF" ] && ! grep -qxF "$SLURM_MARK" "$SLURM_CONF"; then
    echo "setup: $SLURM_CONF exists and was not written by this script; not replacing it (move it away to use the single-node cluster)" >&2
    exit 1
  fi
  conf=$(cat <<EOF
$SLURM_MARK
# A single-node cluster: rewritten by each run of it, kept when a site wrote its own.
ClusterName=mscale
SlurmctldHost=$node(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
StateSaveLocation=$SLURM_DIR/state
SlurmdSpoolDir=$SLURM_DIR/spool
SlurmctldPidFile=$SLURM_DIR/slurmctld.pid
SlurmdPidFile=$SLURM_DIR/slurmd.pid
SlurmctldLogFile=$SLURM_DIR/log/slurmctld.log
SlurmdLogFile=$SLURM_DIR/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MinJobAge=600
KillWait=10
InactiveLimit=0
SlurmctldTimeout=30
SlurmdTimeout=30
NodeName=$node NodeAddr=127.0.0.1 $hw State=UNKNOWN
PartitionName=debug Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF
)
  if [ "$(cat "$SLURM_CONF" 2>/dev/null)" != "$conf" ]; then
    mkdir -p /etc/slurm
    printf '%s\n' "$conf" > "$SLURM_CONF"
    # Daemons started on an older configuration re-read it.
    running "$SLURM_DIR/slurmctld.pid" && scontrol reconfigure >/dev/null 2>&1 || true
  fi
  running "$SLURM_DIR/slurmctld.pid" || slurmctld
  running "$SLURM_DIR/slurmd.pid" || slurmd
  local state=""
  for _ in $(seq 120); do
    state=$(sinfo -h -n "$node" -o %T 2>/dev/null | head -n 1 || true)
    case "$state" in
      idle|mixed|allocated) break ;;
      down*|drain*) scontrol update nodename="$node" state=resume >/dev/null 2>&1 || true ;;
    esac
    sleep 0.5
  done
  case "$state" in
    idle|mixed|allocated) ;;
    *) echo "setup: the Slurm node $node is '${state:-unknown}' after 60 s (logs in $SLURM_DIR/log)" >&2; exit 1 ;;
  esac
  echo "setup: Slurm cluster 'mscale' up: node $node ($hw) $state; state in $SLURM_DIR" >&2
}

slurm_stop() {
  local pidfile pid
  for pidfile in "$SLURM_DIR/slurmd.pid" "$SLURM_DIR/slurmctld.pid"; do
    if running "$pidfile"; then
      pid=$(cat "$pidfile")
      kill -TERM "$pid"
      for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
      kill -0 "$pid" 2>/dev/null && kill -KILL "$pid"
    fi
  done
  # munged: the one started here (its pid file is munge's own).
  if [ -s /run/munge/munged.pid ] && kill -0 "$(cat /run/munge/munged.pid)" 2>/dev/null; then
    kill -TERM "$(cat /run/munge/munged.pid)"
  fi
  echo "setup: Slurm cluster stopped (state kept in $SLURM_DIR)" >&2
}

# cargo-afl (AFL++ built from its own sources with the C compiler, on stable Rust) for the
# coverage-guided fuzz targets of fuzz/ (scripts/afl.sh).
afl_install() {
  command -v cc >/dev/null || need_apt build-essential
  if ! command -v cargo-afl >/dev/null; then
    cargo install cargo-afl --locked --version 0.18.2 >&2
  fi
  # AFL++ itself is built per toolchain on first use; `config --build` does it now.
  cargo afl --version >/dev/null 2>&1 || cargo afl config --build >&2
  echo "setup: $(cargo afl --version)" >&2
}

want="${1:-none}"
case "$want" in
  none)
    echo "setup: the default build needs only cargo; optional: nvrtc, lammps, mpi, browser, python, slurm, slurm-stop, afl, all" ;;
  all|nvrtc|lammps|mpi|browser|python) ;;
  slurm) slurm_start; exit 0 ;;
  slurm-stop) slurm_stop; exit 0 ;;
  afl) afl_install; exit 0 ;;
  *) echo "setup: unknown component '$want' (expected nvrtc, lammps, mpi, browser, python, slurm, slurm-stop, afl or all)" >&2; exit 2 ;;
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
