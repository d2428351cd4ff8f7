#!/usr/bin/env bash
# Sourced by the sbatch scripts here: starts MD worker pools that join an orchestrator.
#   start_pools URL TOKEN_FILE NODE...   (appends the pids of the srun steps to PIDS)
# MSCALE_POOL chooses what a pool is:
#   gpu (default) one md-worker per GPU on the cuda back end, each an MPI job of one rank
#                 (srun --ntasks=1 --gpus-per-task=1); GPU g of a node listens on
#                 MSCALE_WORKER_PORT + g.
#   mpi           one md-worker per node as an MPI job of MSCALE_RANKS_PER_NODE ranks (cargo
#                 feature `mpi`): rank 0 serves and registers, every rank computes its share
#                 of the boxes on the cpu back end.
# Each worker registers under NODE:PORT and heartbeats; the orchestrator spreads a job's boxes
# over the registered workers in proportion to their throughput.
# Reads MSCALE_CA_FILE (the orchestrator's TLS authority), MSCALE_BIN, MSCALE_WORKER_PORT
# (default 50051), MSCALE_SRUN_MPI (default pmix), GPUS_PER_NODE (default 4),
# MSCALE_RANKS_PER_NODE (default: SLURM_NTASKS_PER_NODE or 1).

start_pools() {
  local url="$1" token_file="$2"
  shift 2
  local base="${MSCALE_WORKER_PORT:-50051}" mpi="${MSCALE_SRUN_MPI:-pmix}" node gpu port
  for node in "$@"; do
    case "${MSCALE_POOL:-gpu}" in
      gpu)
        for gpu in $(seq 0 $(( ${GPUS_PER_NODE:-4} - 1 ))); do
          port=$(( base + gpu ))
          srun --nodes=1 --ntasks=1 --nodelist="$node" --gpus-per-task=1 --exact \
            --mpi="$mpi" --kill-on-bad-exit=1 \
            "$MSCALE_BIN/md-worker" serve --listen "0.0.0.0:$port" --device cuda \
            --orchestrator "$url" --advertise "$node:$port" --token-file "$token_file" --ca-file "$MSCALE_CA_FILE" &
          PIDS+=("$!")
        done ;;
      mpi)
        srun --nodes=1 --ntasks="${MSCALE_RANKS_PER_NODE:-${SLURM_NTASKS_PER_NODE:-1}}" \
          --nodelist="$node" --exact --mpi="$mpi" --kill-on-bad-exit=1 \
          "$MSCALE_BIN/md-worker" serve --listen "0.0.0.0:$base" --device cpu \
          --orchestrator "$url" --advertise "$node:$base" --token-file "$token_file" --ca-file "$MSCALE_CA_FILE" &
        PIDS+=("$!") ;;
      *)
        echo "start_pools: MSCALE_POOL=${MSCALE_POOL}: expected gpu or mpi" >&2
        return 2 ;;
    esac
  done
}
