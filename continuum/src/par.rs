//! Deterministic parallel loops over material points.
//!
//! Points are cut into fixed chunks of [`CHUNK`] consecutive points, whatever the number of
//! threads. Per-point work runs chunk by chunk in parallel; scatters to grid nodes go into one
//! buffer per chunk (covering only the node window the chunk touches) and are reduced node by
//! node in chunk order. The arithmetic, and so every bit of the result, is therefore the same
//! for any thread count (the determinism contract of DESIGN.md).

use rayon::prelude::*;
use std::ops::Range;

/// Points per chunk (fixed: results must not depend on the thread count).
pub const CHUNK: usize = 256;

/// Nodes per block in the reduction of a scatter.
const NODE_BLOCK: usize = 1024;

/// Point ranges of the chunks of `n` points.
pub fn chunk_ranges(n: usize) -> Vec<Range<usize>> {
    (0..n.div_ceil(CHUNK)).map(|c| c * CHUNK..((c + 1) * CHUNK).min(n)).collect()
}

/// A chunk's private accumulation buffer over nodes `lo..hi`, `stride` values per node.
pub struct Window<'a> {
    lo: usize,
    hi: usize,
    stride: usize,
    buf: &'a mut [f64],
}

impl Window<'_> {
    /// The values of `node` (must lie in the window the chunk declared).
    #[inline]
    pub fn slot(&mut self, node: usize) -> &mut [f64] {
        debug_assert!(node >= self.lo && node < self.hi, "node {node} outside window {}..{}", self.lo, self.hi);
        let k = (node - self.lo) * self.stride;
        &mut self.buf[k..k + self.stride]
    }
}

/// Reusable buffers of chunked scatters.
#[derive(Debug, Default, Clone)]
pub struct Scatter {
    bufs: Vec<Vec<f64>>,
    spans: Vec<(usize, usize)>,
}

impl Scatter {
    /// Sums per-point contributions into `out` (`n_nodes * stride` values, overwritten).
    /// `span(chunk)` gives the node window `lo..hi` the chunk's points touch; `body(chunk, w)`
    /// adds the chunk's contributions through `w.slot(node)`.
    pub fn run<S, F>(&mut self, n_items: usize, n_nodes: usize, stride: usize, out: &mut Vec<f64>, span: S, body: F)
    where
        S: Fn(Range<usize>) -> (usize, usize) + Sync,
        F: Fn(Range<usize>, &mut Window<'_>) + Sync,
    {
        let ranges = chunk_ranges(n_items);
        self.bufs.resize_with(ranges.len(), Vec::new);
        self.spans.clear();
        self.spans.resize(ranges.len(), (0, 0));
        self.bufs.par_iter_mut().zip(self.spans.par_iter_mut()).zip(ranges.into_par_iter()).for_each(|((buf, sp), r)| {
            let (lo, hi) = span(r.clone());
            let hi = hi.max(lo);
            buf.clear();
            buf.resize((hi - lo) * stride, 0.0);
            body(r, &mut Window { lo, hi, stride, buf });
            *sp = (lo, hi);
        });
        out.clear();
        out.resize(n_nodes * stride, 0.0);
        let (bufs, spans) = (&self.bufs, &self.spans);
        out.par_chunks_mut(NODE_BLOCK * stride).enumerate().for_each(|(b, dst)| {
            let n0 = b * NODE_BLOCK;
            let n1 = n0 + dst.len() / stride;
            for (c, &(lo, hi)) in spans.iter().enumerate() {
                let (a, e) = (lo.max(n0), hi.min(n1));
                if a >= e {
                    continue;
                }
                let src = &bufs[c][(a - lo) * stride..(e - lo) * stride];
                for (d, s) in dst[(a - n0) * stride..(e - n0) * stride].iter_mut().zip(src) {
                    *d += *s;
                }
            }
        });
    }
}

/// Runs `f(chunk_range, chunk_slice)` over the chunks of a per-point array in parallel
/// (`per` values per point).
pub fn for_chunks_mut<T: Send, F>(data: &mut [T], per: usize, f: F)
where
    F: Fn(Range<usize>, &mut [T]) + Sync,
{
    data.par_chunks_mut(CHUNK * per).enumerate().for_each(|(c, s)| {
        let first = c * CHUNK;
        f(first..first + s.len() / per.max(1), s)
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scatter_sums_every_contribution_once_for_any_thread_count() {
        let n = 3 * CHUNK + 17;
        let nodes = 50;
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool");
            pool.install(|| {
                let mut s = Scatter::default();
                let mut out = Vec::new();
                s.run(
                    n,
                    nodes,
                    2,
                    &mut out,
                    |r| ((r.start * 7) % nodes, nodes),
                    |r, w| {
                        for p in r {
                            let node = (p * 7) % nodes;
                            if node >= (p / CHUNK * CHUNK * 7) % nodes {
                                let v = w.slot(node);
                                v[0] += 1.0;
                                v[1] += (p as f64).sqrt();
                            }
                        }
                    },
                );
                out
            })
        };
        let (a, b) = (run(1), run(2));
        assert_eq!(a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), b.iter().map(|v| v.to_bits()).collect::<Vec<_>>());
        let expected: f64 = (0..n).filter(|&p| (p * 7) % nodes >= (p / CHUNK * CHUNK * 7) % nodes).count() as f64;
        assert_eq!(a.iter().step_by(2).sum::<f64>(), expected);
    }
}
