#!/usr/bin/env bash
# The CUDA back end on a real GPU, in one call of the device tool (no Rust toolchain there).
# Built here first (2 cores; the test binaries with MSCALE_REQUIRE_GPU=1 so the `cuda` modules
# are not ignored), stripped, into .gpu/ (listed in .git/info/exclude, carried by the call):
#   export MSCALE_REQUIRE_GPU=1 CARGO_PROFILE_RELEASE_DEBUG=0 CARGO_PROFILE_RELEASE_STRIP=symbols CARGO_TARGET_DIR=target/gpu
#   cargo test --release -p md-worker --features cuda --test physics --test cuda --no-run
#   cargo build --release -p md-worker --features cuda --bin md-worker
#   mkdir -p .gpu && cp target/gpu/release/md-worker .gpu/ &&
#     cp $(ls -t target/gpu/release/deps/physics-* | grep -v '\.d$' | head -1) .gpu/physics &&
#     cp $(ls -t target/gpu/release/deps/cuda-* | grep -v '\.d$' | head -1) .gpu/cuda
# Then: run `bash md-worker/scripts/gpu_check.sh` with carry [".gpu"]. It prints the device,
# the NVRTC it found, the GPU instantiation of the physics suite and tests/cuda.rs, then
# `md-worker bench` on 500- and 108-atom Mishin Cu boxes at 300 K for cuda (double, mixed)
# and the cpu back end on the machine's cores. Logs land in $OUT.
set -uo pipefail
log() { echo "== $*"; }
source "$(dirname "$0")/gpu_env.sh"
log "device"
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv 2>&1 | tee "$OUT/nvidia-smi.txt"
log "nvrtc on the path"
for d in ${LD_LIBRARY_PATH//:/ }; do ls "$d"/libnvrtc* 2>/dev/null; done | head -8
log "physics suite, cuda instantiation"
timeout 240 .gpu/physics cuda:: --test-threads 1 2>&1 | tee "$OUT/physics.log" | tail -40
log "tests/cuda.rs"
timeout 120 .gpu/cuda --test-threads 1 --include-ignored 2>&1 | tee "$OUT/cuda.log" | tail -25
bench() { timeout 120 .gpu/md-worker bench --potential $pot --lattice fcc --a0 3.615 "$@" 2>&1 | tee -a "$OUT/bench.jsonl" | tail -2; }
log "bench (median of 5; one step call of every box per repetition)"
for boxes in 1000 10000; do
  bench --cells 5 --boxes $boxes --steps 100 --device cuda --precision double
  bench --cells 5 --boxes $boxes --steps 100 --device cuda --precision mixed
done
bench --cells 3 --boxes 10000 --steps 100 --device cuda --precision double
bench --cells 3 --boxes 10000 --steps 100 --device cuda --precision mixed
bench --cells 5 --boxes 1000 --steps 100 --device cpu --threads "$(nproc)"
bench --cells 3 --boxes 2000 --steps 100 --device cpu --threads "$(nproc)"
log "done"
