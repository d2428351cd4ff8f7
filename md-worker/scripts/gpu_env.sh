# Sourced by gpu_check.sh, gpu_tune.sh and gpu_ab.sh (on the device machine, in the repository
# root): $OUT, the path the test binaries were built at, NVRTC on the library path, the potential.
OUT=${OUT:-/tmp/gpu-out}
mkdir -p "$OUT"
# The test binaries find their data through the CARGO_MANIFEST_DIR they were built in.
built=/work/main
[ "$PWD" = "$built" ] || { mkdir -p "$(dirname "$built")"; [ -e "$built" ] || ln -s "$PWD" "$built"; }
# cudarc (dynamic loading) looks for libnvrtc.so, libnvrtc.so.12, ...: the CUDA toolkit's and
# the Python wheels' library folders go on the search path.
for d in /usr/local/cuda/lib64 /usr/local/cuda/targets/x86_64-linux/lib \
  $(python3 -c 'import nvidia, os; [print(os.path.join(p, "cuda_nvrtc", "lib")) for p in nvidia.__path__]' 2>/dev/null); do
  [ -d "$d" ] && export LD_LIBRARY_PATH="$d${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
done
export RUST_LOG=warn RUST_BACKTRACE=1
pot=md-worker/potentials/Cu_mishin1.eam.alloy
