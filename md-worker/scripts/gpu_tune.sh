#!/usr/bin/env bash
# Occupancy sweep of the CUDA kernels on a real GPU (one device call; binaries as in
# gpu_check.sh, carried in .gpu/): `md-worker bench` on 5,000 boxes of 500 Mishin Cu atoms
# at 300 K, 100 steps, median of 5, for each NVRTC option set in MSCALE_CUDA_NVRTC_OPTIONS,
# then the GPU physics suite under MSCALE_TUNE_CHECK (default -DMD_MIN_BLOCKS=8). Logs land in $OUT.
set -uo pipefail
source "$(dirname "$0")/gpu_env.sh"
# -DMD_MIN_BLOCKS=N: at least N blocks of 128 threads per SM, i.e. at most 65536 / (128 N)
# registers per thread (kernels.cu). (NVRTC's --maxrregcount did nothing: the PTX is compiled
# by the driver's JIT, which never sees it; tune-maxrregcount.jsonl.)
for opts in "" "-DMD_MIN_BLOCKS=6" "-DMD_MIN_BLOCKS=8" "-DMD_MIN_BLOCKS=10" "-DMD_MIN_BLOCKS=12"; do
  for prec in double mixed; do
    echo "== opts='$opts' $prec"
    MSCALE_CUDA_NVRTC_OPTIONS="$opts" timeout 100 .gpu/md-worker bench --potential $pot --lattice fcc --a0 3.615 \
      --cells 5 --boxes 5000 --steps 100 --device cuda --precision $prec 2>&1 | tee -a "$OUT/tune.jsonl" | tail -1
  done
done
echo "== physics suite on the GPU with ${MSCALE_TUNE_CHECK:--DMD_MIN_BLOCKS=8}"
MSCALE_CUDA_NVRTC_OPTIONS="${MSCALE_TUNE_CHECK:--DMD_MIN_BLOCKS=8}" timeout 120 .gpu/physics cuda:: --test-threads 1 2>&1 | tee "$OUT/physics.log" | tail -4
