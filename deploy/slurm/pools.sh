#!/usr/bin/env bash
# Sourced by the sbatch scripts here: starts MD worker pools that join an orchestrator.
#   start_pools URL TOKEN_FILE NODE...   (appends the pids of the srun steps to PIDS)
# Every pool is one Slurm job step, an MPI job started with `srun --mpi=$MSCALE_SRUN_MPI`, named
# md-worker-NODE-K (so `squeue -s` shows it and `scancel --signal=KILL JOB.STEP` ends it alone).
# MSCALE_POOL chooses what a pool is (default: gpu when the allocation has GPUs, else cpu):
#   gpu  one md-worker per GPU on the cuda back end, each an MPI job of one rank
#        (srun --ntasks=1 --gpus-per-task=1); GPU g of a node listens on MSCALE_WORKER_PORT + g.
#   cpu  MSCALE_POOLS_PER_NODE pools per node (default 1), each an MPI job of
#        MSCALE_RANKS_PER_POOL ranks (default: the node's tasks / the pools) with
#        SLURM_CPUS_PER_TASK threads each; pool k listens on MSCALE_WORKER_PORT + k. Several
#        ranks make one worker with an md-worker built with the cargo feature `mpi` (rank 0
#        serves and registers, every rank computes its share of the boxes); without it, keep
#        one rank per pool.
# (`mpi` is accepted as another name of `cpu`.) Each worker registers under NODE:PORT and
# heartbeats; the orchestrator spreads a job's boxes over the registered workers in proportion
# to their throughput. Reads MSCALE_CA_FILE (the orchestrator's TLS authority), MSCALE_BIN (the
# directory of md-worker), MSCALE_WORKER_PORT (default 50051), MSCALE_SRUN_MPI (default pmix;
# Debian's Open MPI speaks PMIx to srun and has no Slurm PMI-2 client, pmi2 suits MPI libraries built
# with Slurm's PMI-2 such as MPICH),
# GPUS_PER_NODE (default: from SLURM_GPUS_PER_NODE).

start_pools() {
  local url="$1" token_file="$2"
  shift 2
  local base="${MSCALE_WORKER_PORT:-50051}" mpi="${MSCALE_SRUN_MPI:-pmix}" node k port
  local gpus="${GPUS_PER_NODE:-${SLURM_GPUS_PER_NODE:-0}}"
  gpus="${gpus##*:}"
  local kind="${MSCALE_POOL:-}"
  if [ -z "$kind" ]; then
    if [ "${gpus:-0}" -gt 0 ]; then kind=gpu; else kind=cpu; fi
  fi
  local tasks="${SLURM_NTASKS_PER_NODE:-${SLURM_NTASKS:-1}}"
  local pools="${MSCALE_POOLS_PER_NODE:-1}"
  local ranks="${MSCALE_RANKS_PER_POOL:-$(( tasks / pools > 0 ? tasks / pools : 1 ))}"
  local threads="${SLURM_CPUS_PER_TASK:-1}"
  for node in "$@"; do
    case "$kind" in
      gpu)
        for k in $(seq 0 $(( gpus - 1 ))); do
          port=$(( base + k ))
          srun --nodes=1 --ntasks=1 --nodelist="$node" --gpus-per-task=1 --exact \
            --mpi="$mpi" --kill-on-bad-exit=1 --job-name="md-worker-$node-$k" \
            "$MSCALE_BIN/md-worker" serve --listen "0.0.0.0:$port" --device cuda \
            --orchestrator "$url" --advertise "$node:$port" --token-file "$token_file" --ca-file "$MSCALE_CA_FILE" &
          PIDS+=("$!")
        done ;;
      cpu|mpi)
        for k in $(seq 0 $(( pools - 1 ))); do
          port=$(( base + k ))
          srun --nodes=1 --ntasks="$ranks" --cpus-per-task="$threads" --nodelist="$node" --exact \
            --mpi="$mpi" --kill-on-bad-exit=1 --job-name="md-worker-$node-$k" \
            "$MSCALE_BIN/md-worker" serve --listen "0.0.0.0:$port" --device cpu --threads "$threads" \
            --orchestrator "$url" --advertise "$node:$port" --token-file "$token_file" --ca-file "$MSCALE_CA_FILE" &
          PIDS+=("$!")
        done ;;
      *)
        echo "start_pools: MSCALE_POOL=$kind: expected gpu or cpu" >&2
        return 2 ;;
    esac
  done
}
