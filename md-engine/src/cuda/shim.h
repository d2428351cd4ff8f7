// Host build of kernels.cu (MSCALE_HOST): the CUDA execution model as plain loops, so the
// very same kernel source runs on the CPU in tests. A block is a function call (blocks run
// one after another), a phase (FOR_THREADS ... END_THREADS) is a loop over the block's
// threads in order, so every thread finishes a phase before any starts the next, which is
// what the barrier guarantees on the device. Shared memory is a local struct; the kernels
// use no atomics (the few benign "any thread sets a flag" writes are plain stores).
#pragma once
#include <cmath>

using std::ceil;
using std::exp;
using std::floor;
using std::sqrt;

#define DEVICE static
#define FOR_THREADS(t) for (int t = 0; t < MD_NT; ++t) {
#define END_THREADS }
#define UNIFORM_READ_DONE()
#define SHARED_DECL(T, v) T v
#define BLOCK_INDEX block_index_
#define KERNEL_ENTRY(name)                                                  \
    static void name##_host_block(const Params& p, int block_index_);            \
    extern "C" void mscale_host_##name(const Params* pp, int nblocks) {     \
        for (int b = 0; b < nblocks; ++b) name##_host_block(*pp, b);            \
    }                                                                       \
    static void name##_host_block(const Params& p, int block_index_)
