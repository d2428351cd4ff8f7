#!/usr/bin/env bash
# A/B of two md-worker builds on one GPU machine (one device call): .gpu/md-worker-old and
# .gpu/md-worker-new (built as in gpu_check.sh from the two sources), interleaved, 4 runs each,
# `md-worker bench` on 5,000 boxes of 500 Mishin Cu atoms at 300 K, 100 steps (each run
# prints the median of 5 step calls). Logs land in $OUT.
set -uo pipefail
source "$(dirname "$0")/gpu_env.sh"
for i in 1 2 3 4; do
  for v in old new; do
    r=$(timeout 60 .gpu/md-worker-$v bench --potential $pot --lattice fcc --a0 3.615 --cells 5 --boxes 5000 --steps 100 \
      --device cuda --precision ${MSCALE_AB_PRECISION:-double} 2>&1 | tail -1)
    echo "{\"build\":\"$v\",\"run\":$i,\"result\":$r}" | tee -a "$OUT/ab.jsonl"
  done
done
