//! Deterministic parallel loops over material points.
//!
//! Points are cut into fixed chunks of [`CHUNK`] consecutive points, whatever the number of
//! threads. Per-point work runs chunk by chunk in parallel. The explicit step's scatters to
//! grid nodes ([`Scatter::run_tiled`]) are summed in an order fixed by space instead, so that
//! the same order can be kept when the points are spread over MPI ranks: the grid is cut into
//! [`Tiles`], slabs of [`tile_cells`] cells along its slowest axis (the last); a point belongs
//! to the slab of the cell holding its position at the start of the step; each tile sums its
//! points in ascending point index into a buffer over the node window its points touch, and
//! the tiles' buffers are added node by node in tile order. A node's value is then
//! `((0 + T_a) + T_b) + ...` over the tiles that touch it, each `T` summed from 0 in point
//! order: it depends neither on the thread count nor on which process computed which tile
//! (the determinism contract of DESIGN.md). [`Scatter::run`] keeps the older chunk order (the
//! implicit step's own assemblies and tests use it; they are single-process).

use rayon::prelude::*;
use std::ops::Range;

/// Points per chunk (fixed: results must not depend on the thread count).
pub const CHUNK: usize = 256;

/// Nodes per block in the reduction of a scatter.
const NODE_BLOCK: usize = 1024;

/// Cells of the grid's slowest axis per tile in a `dim`-dimensional grid (fixed by the
/// dimension: results must not depend on the number of threads or ranks). Slabs keep each
/// tile's node window one contiguous range of linear node indices (axis 0 varies fastest), so a
/// tile's buffer holds no nodes it cannot touch beyond the stencil's reach, in 1D, 2D and 3D
/// alike. 4 cells in 1D (a slab there is a handful of points); 2 in 2D and 3D, where a grid has
/// few rows along its last axis: the tiles are what ranks are balanced by, and a slab of 4 rows of
/// the jet piled against its wall held 11 % of the body (continuum/README.md "MPI", slab
/// granularity). A thinner slab's buffer carries relatively more of the stencil's reach (+30 %
/// bytes on the jet layout).
pub const fn tile_cells(dim: usize) -> usize {
    if dim == 1 { 4 } else { 2 }
}

/// [`Tiles`]'s mark of a point in no tile.
const NO_TILE: u32 = u32::MAX;

/// The points of each tile, each tile's in ascending point index (a counting sort of the
/// points by tile, rebuilt every step).
#[derive(Debug, Default, Clone)]
pub struct Tiles {
    start: Vec<usize>,
    order: Vec<usize>,
    tile: Vec<u32>,
    /// Over MPI ranks: rank `r` owns tiles `cuts[r]..cuts[r + 1]` ([`Tiles::set_cuts`]); empty:
    /// the even blocks of [`tile_owner`]. Kept by [`Tiles::assign`].
    cuts: Vec<usize>,
}

impl Tiles {
    /// Sorts points `0..n` into `n_tiles` tiles, point `p` into `tile_of(p)` (< `n_tiles`).
    pub fn assign(&mut self, n_tiles: usize, n: usize, tile_of: impl Fn(usize) -> usize + Sync) {
        self.assign_some(n_tiles, n, |p| Some(tile_of(p)));
    }

    /// As [`Tiles::assign`], the points for which `tile_of` gives `None` in no tile (over MPI
    /// ranks: the points another rank holds).
    pub fn assign_some(&mut self, n_tiles: usize, n: usize, tile_of: impl Fn(usize) -> Option<usize> + Sync) {
        self.tile.clear();
        self.tile.par_extend((0..n).into_par_iter().with_min_len(CHUNK).map(|p| match tile_of(p) {
            Some(t) => {
                assert!(t < n_tiles, "point {p} in tile {t} of {n_tiles}");
                t as u32
            }
            None => NO_TILE,
        }));
        self.start.clear();
        self.start.resize(n_tiles + 1, 0);
        for &t in self.tile.iter().filter(|&&t| t != NO_TILE) {
            self.start[t as usize + 1] += 1;
        }
        for t in 0..n_tiles {
            self.start[t + 1] += self.start[t];
        }
        let mut next = self.start[..n_tiles].to_vec();
        self.order.clear();
        self.order.resize(self.start[n_tiles], 0);
        for (p, &t) in self.tile.iter().enumerate().filter(|(_, t)| **t != NO_TILE) {
            self.order[next[t as usize]] = p;
            next[t as usize] += 1;
        }
    }

    /// Keeps only the points of the tiles for which `keep(tile)` holds (the tiles a rank owns);
    /// the others become empty. Points keep their order.
    pub fn restrict(&self, keep: impl Fn(usize) -> bool) -> Tiles {
        let mut out = Tiles { start: vec![0], order: Vec::new(), tile: self.tile.clone(), cuts: self.cuts.clone() };
        for t in 0..self.count() {
            if keep(t) {
                out.order.extend_from_slice(self.points(t));
            }
            out.start.push(out.order.len());
        }
        out
    }

    /// Number of tiles.
    pub fn count(&self) -> usize {
        self.start.len().saturating_sub(1)
    }

    /// The points of tile `t`, in ascending index.
    pub fn points(&self, t: usize) -> &[usize] {
        &self.order[self.start[t]..self.start[t + 1]]
    }

    /// The tile of point `p` (as last assigned; `None`: in no tile, [`Tiles::assign_some`]).
    pub fn tile_of(&self, p: usize) -> Option<usize> {
        self.tile.get(p).filter(|&&t| t != NO_TILE).map(|&t| t as usize)
    }

    /// The rank owning tile `t` over `ranks` ranks: the block of [`Tiles::set_cuts`] holding
    /// it, or the even blocks of [`tile_owner`] when no cuts for `ranks` ranks are set.
    pub fn owner(&self, t: usize, ranks: usize) -> usize {
        if self.cuts.len() == ranks + 1 {
            self.cuts[1..].partition_point(|&c| c <= t).min(ranks - 1)
        } else {
            tile_owner(t, self.count(), ranks)
        }
    }

    /// The tiles rank `rank` of `ranks` owns ([`Tiles::owner`]), in tile order.
    pub fn owned_by(&self, rank: usize, ranks: usize) -> impl Iterator<Item = usize> + '_ {
        (0..self.count()).filter(move |&t| self.owner(t, ranks) == rank)
    }

    /// Gives rank `r` the tiles `cuts[r]..cuts[r + 1]` from now on (`cuts` ascending from 0 to
    /// the tile count, one more entry than ranks; see [`balanced_cuts`]; empty: the even blocks
    /// again). Which rank sums a
    /// tile never changes a result (the module's documentation), only who does the work.
    pub fn set_cuts(&mut self, cuts: Vec<usize>) {
        debug_assert!(cuts.is_empty() || (cuts[0] == 0 && cuts.windows(2).all(|w| w[0] <= w[1])));
        self.cuts = cuts;
    }

    /// The cuts set by [`Tiles::set_cuts`] (empty: the even blocks).
    pub fn cuts(&self) -> &[usize] {
        &self.cuts
    }
}

/// Contiguous blocks of tiles for `ranks` ranks whose largest summed `cost` is the smallest
/// any contiguous split reaches (to 1e-9 of it): the returned `cuts` (`ranks + 1` entries,
/// `cuts[0] = 0`, last `cost.len()`) give rank `r` the tiles `cuts[r]..cuts[r + 1]`. A
/// bisection on the bottleneck, each probe a greedy left-to-right fill; the cuts depend only
/// on `cost`, so every rank computing them from the same costs gets the same split.
pub fn balanced_cuts(cost: &[f64], ranks: usize) -> Vec<usize> {
    let ranks = ranks.max(1);
    let fill = |cap: f64| -> Option<Vec<usize>> {
        let mut cuts = vec![0];
        let mut load = 0.0;
        for (t, &c) in cost.iter().enumerate() {
            if load + c > cap && t > *cuts.last().unwrap_or(&0) {
                if cuts.len() == ranks {
                    return None;
                }
                cuts.push(t);
                load = 0.0;
            }
            load += c;
        }
        cuts.resize(ranks + 1, cost.len());
        Some(cuts)
    };
    let total: f64 = cost.iter().sum();
    let (mut lo, mut hi) = (cost.iter().copied().fold(0.0, f64::max), total);
    if !(total > 0.0 && total.is_finite()) {
        return (0..=ranks).map(|r| (r * cost.len()).div_ceil(ranks)).collect();
    }
    for _ in 0..100 {
        if hi - lo <= 1e-9 * hi {
            break;
        }
        let mid = 0.5 * (lo + hi);
        if fill(mid).is_some() { hi = mid } else { lo = mid }
    }
    fill(hi).unwrap_or_else(|| (0..=ranks).map(|r| (r * cost.len()).div_ceil(ranks)).collect())
}

/// The slab tile of a position: `tile_cells(D)` cells of the last axis per tile, clamped into the
/// grid (a point outside it is the stencil's error to report), and the number of tiles.
pub fn slab_tile<const D: usize>(grid: &crate::grid::Grid<D>, x: &[f64; D]) -> usize {
    let a = D - 1;
    let cell = ((x[a] - grid.origin[a]) / grid.h[a]).floor();
    let cell = if cell.is_finite() { cell.clamp(0.0, (grid.cells[a].max(1) - 1) as f64) as usize } else { 0 };
    cell / tile_cells(D)
}

/// Number of slab tiles of a grid.
pub fn slab_tile_count<const D: usize>(grid: &crate::grid::Grid<D>) -> usize {
    grid.cells[D - 1].max(1).div_ceil(tile_cells(D))
}

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
        reduce_in_order(&self.bufs, &self.spans, n_nodes, stride, out);
    }

    /// Sums per-point contributions into `out` (`n_nodes * stride` values, overwritten) in
    /// tile order (see the module's documentation). `span(p)` gives the node window `lo..hi`
    /// point `p` touches; `body(points, w)` adds the contributions of one tile's points (in
    /// the order given) through `w.slot(node)`.
    pub fn run_tiled<S, F>(&mut self, tiles: &Tiles, n_nodes: usize, stride: usize, out: &mut Vec<f64>, span: S, body: F)
    where
        S: Fn(usize) -> (usize, usize) + Sync,
        F: Fn(&[usize], &mut Window<'_>) + Sync,
    {
        match exchange().filter(|e| e.size() > 1) {
            None => self.tile_buffers(tiles, stride, span, body),
            Some(ex) => {
                let (rank, size) = (ex.rank(), ex.size());
                let mine = tiles.restrict(|t| tiles.owner(t, size) == rank);
                self.tile_buffers(&mine, stride, span, body);
                self.share_tiles(ex, tiles, stride);
            }
        }
        reduce_in_order(&self.bufs, &self.spans, n_nodes, stride, out);
    }

    /// Replaces every tile's buffer by its owner's (all ranks end with the same buffers): each
    /// rank packs the tiles it owns as `[tile, lo, hi, values...]` (integers exact in f64),
    /// the packs are all-gathered, and every rank unpacks all of them.
    fn share_tiles(&mut self, ex: &dyn TileExchange, tiles: &Tiles, stride: usize) {
        let mut pack = Vec::new();
        for t in tiles.owned_by(ex.rank(), ex.size()) {
            let (lo, hi) = self.spans[t];
            pack.extend([t as f64, lo as f64, hi as f64]);
            pack.extend_from_slice(&self.bufs[t]);
        }
        let all = ex.all_gather(&pack);
        for r in &all {
            let mut k = 0;
            while k < r.len() {
                let (t, lo, hi) = (r[k] as usize, r[k + 1] as usize, r[k + 2] as usize);
                k += 3;
                let len = (hi - lo) * stride;
                self.spans[t] = (lo, hi);
                self.bufs[t].clear();
                self.bufs[t].extend_from_slice(&r[k..k + len]);
                k += len;
            }
        }
    }

    /// The first half of [`Scatter::run_tiled`]: fills one buffer per tile (read them with
    /// [`Scatter::buffer`]). A process that owns some of the tiles fills these, exchanges the
    /// ones other processes need, and reduces with [`reduce_in_order`].
    pub fn tile_buffers<S, F>(&mut self, tiles: &Tiles, stride: usize, span: S, body: F)
    where
        S: Fn(usize) -> (usize, usize) + Sync,
        F: Fn(&[usize], &mut Window<'_>) + Sync,
    {
        let nt = tiles.count();
        self.bufs.resize_with(nt, Vec::new);
        self.bufs.truncate(nt);
        self.spans.clear();
        self.spans.resize(nt, (0, 0));
        self.bufs.par_iter_mut().zip(self.spans.par_iter_mut()).enumerate().for_each(|(t, (buf, sp))| {
            let pts = tiles.points(t);
            let (mut lo, mut hi) = (usize::MAX, 0);
            for &p in pts {
                let (a, b) = span(p);
                if a < b {
                    lo = lo.min(a);
                    hi = hi.max(b);
                }
            }
            if lo >= hi {
                (lo, hi) = (0, 0);
            }
            buf.clear();
            buf.resize((hi - lo) * stride, 0.0);
            if lo < hi {
                body(pts, &mut Window { lo, hi, stride, buf });
            }
            *sp = (lo, hi);
        });
    }

    /// Tile `t`'s node window and buffer after [`Scatter::tile_buffers`].
    pub fn buffer(&self, t: usize) -> ((usize, usize), &[f64]) {
        (self.spans[t], &self.bufs[t])
    }
}

/// The processes a scatter's tiles are spread over (MPI ranks under the feature `mpi`, see
/// [`set_exchange`]); every rank calls [`TileExchange::all_gather`] at the same points of the
/// step, in the same order.
pub trait TileExchange: Send + Sync {
    /// This process's rank, `0..size()`.
    fn rank(&self) -> usize;
    /// The number of processes.
    fn size(&self) -> usize;
    /// Every rank's `mine`, in rank order (a collective: every rank calls it).
    fn all_gather(&self, mine: &[f64]) -> Vec<Vec<f64>>;
    /// Every rank's `mine` bytes, in rank order (a collective: every rank calls it); the
    /// solver's agreement on a failure (which point, which message).
    fn all_gather_bytes(&self, mine: &[u8]) -> Vec<Vec<u8>>;
    /// What this rank's collectives cost so far.
    fn stats(&self) -> ExchangeStats {
        ExchangeStats::default()
    }
}

/// The traffic of one rank's collectives since the start: calls, bytes this rank sent (its
/// own contribution, once per call) and received (the other ranks' contributions), and the
/// wall time spent inside the collectives (waiting for the slowest rank included).
#[derive(Debug, Default, Clone, Copy, PartialEq)]
pub struct ExchangeStats {
    pub calls: u64,
    pub bytes_sent: u64,
    pub bytes_received: u64,
    pub seconds: f64,
}

/// Per point whether the rank `rank` of `ranks` owns it: the points of the tiles it owns
/// ([`Tiles::owner`]), the tiles [`Scatter::run_tiled`] fills on that rank.
pub fn owned_points(tiles: &Tiles, rank: usize, ranks: usize, out: &mut Vec<bool>) {
    out.clear();
    out.resize(tiles.tile.len(), false);
    for t in tiles.owned_by(rank, ranks) {
        for &p in tiles.points(t) {
            out[p] = true;
        }
    }
}

static EXCHANGE: std::sync::OnceLock<Box<dyn TileExchange>> = std::sync::OnceLock::new();

/// Spreads the tiles of every [`Scatter::run_tiled`] of this process over `ex`'s ranks from now
/// on (once per process; `Err` gives `ex` back if one is set already). Each rank then fills the
/// buffers of the tiles it owns ([`tile_owner`]) from their points only, the buffers are
/// all-gathered and reduced in tile order as on one process: the same bits.
pub fn set_exchange(ex: Box<dyn TileExchange>) -> Result<(), Box<dyn TileExchange>> {
    EXCHANGE.set(ex)
}

/// The exchange set by [`set_exchange`], if any.
pub fn exchange() -> Option<&'static dyn TileExchange> {
    EXCHANGE.get().map(|b| b.as_ref())
}

/// The rank owning tile `t` of `n_tiles` over `ranks` ranks before any [`Tiles::set_cuts`]:
/// contiguous blocks of tiles, as even as the tile count allows.
pub fn tile_owner(t: usize, n_tiles: usize, ranks: usize) -> usize {
    (t * ranks / n_tiles.max(1)).min(ranks.saturating_sub(1))
}

/// Adds the buffers `bufs[k]` (over node windows `spans[k]`, `stride` values per node) into
/// `out` (`n_nodes * stride` values, overwritten), node by node in the order of `k`: each node
/// is `((0 + b_first) + b_next) + ...` over the buffers whose window holds it, whatever the
/// thread count.
pub fn reduce_in_order<B: AsRef<[f64]> + Sync>(bufs: &[B], spans: &[(usize, usize)], n_nodes: usize, stride: usize, out: &mut Vec<f64>) {
    out.clear();
    out.resize(n_nodes * stride, 0.0);
    out.par_chunks_mut(NODE_BLOCK * stride).enumerate().for_each(|(b, dst)| {
        let n0 = b * NODE_BLOCK;
        let n1 = n0 + dst.len() / stride;
        for (c, &(lo, hi)) in spans.iter().enumerate() {
            let (a, e) = (lo.max(n0), hi.min(n1));
            if a >= e {
                continue;
            }
            let src = &bufs[c].as_ref()[(a - lo) * stride..(e - lo) * stride];
            for (d, s) in dst[(a - n0) * stride..(e - n0) * stride].iter_mut().zip(src) {
                *d += *s;
            }
        }
    });
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

    /// Points of a 2D grid of 10 x 21 cells (slab tiles of [`tile_cells`] rows), each touching
    /// the four nodes of its cell and their right neighbours, with values far apart in
    /// magnitude so that any change of summation order shows in the bits.
    fn tiled_case() -> (crate::grid::Grid<2>, Vec<[f64; 2]>, Vec<f64>) {
        use crate::grid::{Face, Grid};
        let grid =
            Grid::<2> { origin: [0.0; 2], h: [0.1, 0.05], cells: [10, 21], faces: [(Face::Free, Face::Free), (Face::Free, Face::Free)] };
        let mut state = 0x9e3779b97f4a7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let n = 2000;
        let x: Vec<[f64; 2]> = (0..n).map(|_| [0.999 * next(), 1.049 * next()]).collect();
        let val: Vec<f64> = (0..n).map(|_| (next() - 0.3) * 10f64.powi((next() * 12.0) as i32 - 6)).collect();
        (grid, x, val)
    }

    fn touched(grid: &crate::grid::Grid<2>, x: &[f64; 2]) -> Vec<usize> {
        let (i, j) = ((x[0] / grid.h[0]).floor() as usize, (x[1] / grid.h[1]).floor() as usize);
        let mut v = Vec::new();
        for dj in 0..2 {
            for di in 0..3 {
                if i + di <= grid.cells[0] {
                    v.push(grid.linear([i + di, j + dj]));
                }
            }
        }
        v
    }

    #[test]
    fn tiled_scatter_sums_in_tile_order_for_any_thread_count_and_tile_owner() {
        let (grid, x, val) = tiled_case();
        let n = x.len();
        let nodes = grid.node_count();
        let mut tiles = Tiles::default();
        tiles.assign(slab_tile_count(&grid), n, |p| slab_tile(&grid, &x[p]));
        let nt = tiles.count();
        assert_eq!(nt, 21usize.div_ceil(tile_cells(2)));
        let span = |p: usize| {
            let t = touched(&grid, &x[p]);
            (*t.iter().min().unwrap(), t.iter().max().unwrap() + 1)
        };
        let body = |pts: &[usize], w: &mut Window<'_>| {
            for &p in pts {
                for (k, i) in touched(&grid, &x[p]).into_iter().enumerate() {
                    let s = w.slot(i);
                    s[0] += val[p] * (1.0 + 0.1 * k as f64);
                    s[1] += 1.0;
                }
            }
        };
        let bits = |v: &[f64]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        let single = |threads: usize| {
            rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("pool").install(|| {
                let mut out = Vec::new();
                Scatter::default().run_tiled(&tiles, nodes, 2, &mut out, span, body);
                out
            })
        };
        let one = single(1);
        assert_eq!(bits(&one), bits(&single(2)));
        assert_eq!(bits(&one), bits(&single(3)));
        // The order written out: per node, tiles in order, each tile's points in index order.
        let mut expected = vec![0.0; nodes];
        for t in 0..tiles.count() {
            let mut part = vec![0.0; nodes];
            for p in (0..n).filter(|&p| tiles.tile_of(p) == Some(t)) {
                for (k, i) in touched(&grid, &x[p]).into_iter().enumerate() {
                    part[i] += val[p] * (1.0 + 0.1 * k as f64);
                }
            }
            for i in 0..nodes {
                if part[i] != 0.0 {
                    expected[i] += part[i];
                }
            }
        }
        assert_eq!(bits(&one.iter().step_by(2).copied().collect::<Vec<_>>()), bits(&expected));
        assert_eq!(one.iter().skip(1).step_by(2).sum::<f64>(), 6.0 * n as f64 - 2.0 * x.iter().filter(|x| x[0] >= 0.9).count() as f64);
        // Tiles spread over 1 to 4 "ranks" in contiguous and scattered assignments: each rank
        // fills only its own tiles' buffers from only its own points; the buffers gathered in
        // tile order reduce to the single-process bits.
        for ranks in 1..=4usize {
            for owner in
                [Box::new(move |t: usize| t * ranks / nt) as Box<dyn Fn(usize) -> usize>, Box::new(move |t: usize| (t * 5 + 1) % ranks)]
            {
                let mut gathered: Vec<Option<((usize, usize), Vec<f64>)>> = vec![None; tiles.count()];
                for r in 0..ranks {
                    let mine = tiles.restrict(|t| owner(t) == r);
                    let mut sc = Scatter::default();
                    sc.tile_buffers(&mine, 2, span, body);
                    for (t, slot) in gathered.iter_mut().enumerate().filter(|(t, _)| owner(*t) == r) {
                        let (sp, b) = sc.buffer(t);
                        *slot = Some((sp, b.to_vec()));
                    }
                }
                let (spans, bufs): (Vec<_>, Vec<_>) = gathered.into_iter().map(|g| g.expect("every tile has an owner")).unzip();
                let mut out = Vec::new();
                reduce_in_order(&bufs, &spans, nodes, 2, &mut out);
                assert_eq!(bits(&out), bits(&one), "{ranks} ranks");
            }
        }
    }

    #[test]
    fn balanced_cuts_minimise_the_largest_block_and_set_the_owners() {
        // The smallest bottleneck of a contiguous split, by brute force over every split.
        fn best(cost: &[f64], ranks: usize) -> f64 {
            fn go(cost: &[f64], ranks: usize) -> f64 {
                if ranks == 1 {
                    return cost.iter().sum();
                }
                (0..=cost.len()).map(|k| cost[..k].iter().sum::<f64>().max(go(&cost[k..], ranks - 1))).fold(f64::INFINITY, f64::min)
            }
            go(cost, ranks)
        }
        let block = |cost: &[f64], cuts: &[usize], r: usize| cost[cuts[r]..cuts[r + 1]].iter().sum::<f64>();
        let cases: [&[f64]; 5] = [
            &[1.0; 16],
            &[9.0, 9.0, 9.0, 9.0, 9.0, 9.0, 9.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            &[0.0, 5.0, 1.0, 1.0, 7.0, 0.5, 2.0],
            &[3.0],
            &[0.0; 4],
        ];
        for cost in cases {
            for ranks in 1..=4 {
                let cuts = balanced_cuts(cost, ranks);
                assert_eq!(cuts.len(), ranks + 1);
                assert_eq!((cuts[0], cuts[ranks]), (0, cost.len()));
                assert!(cuts.windows(2).all(|w| w[0] <= w[1]), "{cuts:?}");
                let worst = (0..ranks).map(|r| block(cost, &cuts, r)).fold(0.0, f64::max);
                assert!(worst <= best(cost, ranks) * (1.0 + 1e-9), "{cost:?} over {ranks}: {cuts:?} gives {worst}");
                let mut tiles = Tiles::default();
                tiles.assign(cost.len(), 0, |_| 0);
                tiles.set_cuts(cuts.clone());
                for t in 0..cost.len() {
                    let r = tiles.owner(t, ranks);
                    assert!(cuts[r] <= t && t < cuts[r + 1], "tile {t} given to rank {r} by {cuts:?}");
                }
                // Without cuts for this rank count, the even blocks.
                tiles.set_cuts(Vec::new());
                assert!((0..cost.len()).all(|t| tiles.owner(t, ranks) == tile_owner(t, cost.len(), ranks)));
            }
        }
        // The jet-like case: heavy tiles first, light after: 2 ranks split the weight, not the count.
        let jet = [9.0, 9.0, 9.0, 9.0, 9.0, 9.0, 9.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert_eq!(balanced_cuts(&jet, 2), vec![0, 4, 13]);
        let even: f64 = (0..jet.len()).filter(|&t| tile_owner(t, jet.len(), 2) == 0).map(|t| jet[t]).sum();
        assert_eq!((even, block(&jet, &balanced_cuts(&jet, 2), 0)), (63.0, 36.0));
    }
}
