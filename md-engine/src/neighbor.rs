//! Half neighbour lists with explicit periodic images.
//!
//! A pair is stored once as (i, j, n): atom j's image at `x_j + n * L` lies within
//! `cutoff + skin` of atom i. A box shorter than twice the cut-off simply has several
//! entries for the same j with different n, so forces stay exact for any box size.
//! Images are integers, so the list stays valid while the box is stretched. Each pair
//! stores its image as a 16-bit code into a small dense table (`images`), so a pair costs
//! 6 bytes and the force kernel turns codes into displacement shifts `n * L` once per step.

use serde::{Deserialize, Serialize};

/// Neighbour list of one box, CSR layout (`start[i]..start[i+1]` indexes `j` and `code`).
/// An empty `start` means "not built" (lists of idle boxes are released to save memory).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct NeighborList {
    /// Row starts, length n_atoms + 1 (empty when not built).
    pub start: Vec<u32>,
    /// Neighbour atom (box-local index).
    pub j: Vec<u32>,
    /// Image of the neighbour, as an index into `images`.
    pub code: Vec<u16>,
    /// Image vectors n (in box lengths) by code.
    pub images: Vec<[i32; 3]>,
    /// Which build this is (unique in the process; 0: never built): the threaded kernel keys
    /// its blocks' windows on it (`intra.rs`). Not saved.
    #[serde(skip)]
    pub generation: u64,
}

impl NeighborList {
    /// Whether the list is built for `n` atoms.
    pub fn is_built(&self, n: usize) -> bool {
        self.start.len() == n + 1
    }

    /// Drop the list and give its memory back.
    pub fn release(&mut self) {
        *self = NeighborList::default();
    }

    /// Pairs in the list.
    pub fn len(&self) -> usize {
        self.j.len()
    }

    /// Whether the list holds no pair.
    pub fn is_empty(&self) -> bool {
        self.j.is_empty()
    }
}

/// The smallest box side (A) the list serves for a neighbour radius `rs`: `rs / 16`, so at
/// most 33 images per axis and 33^3 < 65536 image codes ([`build`] would panic beyond). The
/// engine refuses smaller boxes at input and stops a box that shrinks below it.
pub fn min_box_side(rs: f64) -> f64 {
    rs / 16.0
}

/// Build the half list of atoms at `x` (already wrapped into `[lo, lo + l)`) with radius `rs`.
/// Bins are at least `rs / 2` wide. Rows are sorted by distance (ties by atom and image),
/// so the same input gives the same list.
///
/// # Panics
/// If a box is so small against `rs` that more than 65536 images would be needed
/// (a box side below ~rs / 19, far from any physical box).
pub fn build(x: &[[f64; 3]], lo: [f64; 3], l: [f64; 3], rs: f64, list: &mut NeighborList) {
    static BUILDS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
    list.generation = BUILDS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let n = x.len();
    let mut nc = [1usize; 3];
    let mut reach = [1i32; 3];
    let mut half = [0i32; 3]; // largest |image| per axis
    for d in 0..3 {
        nc[d] = ((2.0 * l[d] / rs).floor() as usize).clamp(1, 1 << 10);
        let cell = l[d] / nc[d] as f64;
        reach[d] = (rs / cell).ceil() as i32;
        half[d] = (reach[d] + nc[d] as i32 - 1) / nc[d] as i32;
    }
    let span = [2 * half[0] + 1, 2 * half[1] + 1, 2 * half[2] + 1];
    let ncodes = (span[0] * span[1] * span[2]) as usize;
    assert!(ncodes <= 1 << 16, "box {l:?} too small for a neighbour radius of {rs} A");
    list.images.clear();
    for a in -half[0]..=half[0] {
        for b in -half[1]..=half[1] {
            for c in -half[2]..=half[2] {
                list.images.push([a, b, c]);
            }
        }
    }
    let code_of = |img: [i32; 3]| (((img[0] + half[0]) * span[1] + img[1] + half[1]) * span[2] + img[2] + half[2]) as u16;
    let ncell = nc[0] * nc[1] * nc[2];
    let cell_of = |p: &[f64; 3]| -> [usize; 3] {
        let mut c = [0usize; 3];
        for d in 0..3 {
            let s = ((p[d] - lo[d]) / l[d] * nc[d] as f64).floor() as i64;
            c[d] = s.clamp(0, nc[d] as i64 - 1) as usize;
        }
        c
    };
    // Counting sort of atoms into cells, atoms in index order inside a cell.
    let mut count = vec![0u32; ncell + 1];
    let cells: Vec<[usize; 3]> = x.iter().map(cell_of).collect();
    let flat = |c: [usize; 3]| (c[0] * nc[1] + c[1]) * nc[2] + c[2];
    for c in &cells {
        count[flat(*c) + 1] += 1;
    }
    for k in 0..ncell {
        count[k + 1] += count[k];
    }
    let mut fill = count.clone();
    let mut order = vec![0u32; n];
    for (i, c) in cells.iter().enumerate() {
        let f = flat(*c);
        order[fill[f] as usize] = i as u32;
        fill[f] += 1;
    }
    // Stencil: wrapped cell offset and image per axis, precomputed once per cell row.
    let rs2 = rs * rs;
    list.start.clear();
    list.j.clear();
    list.code.clear();
    list.start.reserve(n + 1);
    list.start.push(0);
    let mut stencil: [Vec<(usize, i32)>; 3] = Default::default();
    // A row entry packed as (r^2 bits, j, code): r^2 >= +0, so its bits order as the value
    // and one integer sort gives the (r^2, j, image) order.
    let mut row: Vec<u128> = Vec::new();
    for i in 0..n {
        row.clear();
        let ci = cells[i];
        let xi = x[i];
        for d in 0..3 {
            stencil[d].clear();
            for o in -reach[d]..=reach[d] {
                let c = ci[d] as i32 + o;
                stencil[d].push((c.rem_euclid(nc[d] as i32) as usize, c.div_euclid(nc[d] as i32)));
            }
        }
        for &(cx, ix) in &stencil[0] {
            let sx = ix as f64 * l[0] - xi[0];
            for &(cy, iy) in &stencil[1] {
                let sy = iy as f64 * l[1] - xi[1];
                for &(cz, iz) in &stencil[2] {
                    let sz = iz as f64 * l[2] - xi[2];
                    let img = [ix, iy, iz];
                    let self_image_kept = img > [0, 0, 0];
                    let f = flat([cx, cy, cz]);
                    for &j in &order[count[f] as usize..count[f + 1] as usize] {
                        let ju = j as usize;
                        if !(ju > i || (ju == i && self_image_kept)) {
                            continue;
                        }
                        let p = x[ju];
                        let (dx, dy, dz) = (p[0] + sx, p[1] + sy, p[2] + sz);
                        let r2 = dx * dx + dy * dy + dz * dz;
                        if r2 < rs2 {
                            row.push(((r2.to_bits() as u128) << 64) | ((j as u128) << 16) | code_of(img) as u128);
                        }
                    }
                }
            }
        }
        // Nearest first: the kernel's cut-off test then mostly goes one way per row, and
        // spline rows are read in increasing order. Ties broken by (j, image): a total order.
        row.sort_unstable();
        for &e in &row {
            list.j.push((e >> 16) as u32);
            list.code.push(e as u16);
        }
        list.start.push(list.j.len() as u32);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rows [`build`] must give: every (j, image) within `rs` by brute force over images,
    /// half by (j > i, or j == i with image > 0), sorted by (r^2, j, code).
    fn brute(x: &[[f64; 3]], l: [f64; 3], rs: f64, list: &NeighborList) -> Vec<Vec<(u32, u16)>> {
        let code_of = |img: [i32; 3]| list.images.iter().position(|n| *n == img).map(|c| c as u16);
        // One image beyond the table on every axis: a pair in range there fails the test.
        let h = list.images[0].map(|c| 1 - c);
        (0..x.len())
            .map(|i| {
                let mut row: Vec<(f64, u32, u16)> = Vec::new();
                for j in i..x.len() {
                    for a in -h[0]..=h[0] {
                        for b in -h[1]..=h[1] {
                            for c in -h[2]..=h[2] {
                                let img = [a, b, c];
                                if j == i && img <= [0, 0, 0] {
                                    continue;
                                }
                                let d: [f64; 3] = std::array::from_fn(|k| x[j][k] + (img[k] as f64 * l[k] - x[i][k]));
                                let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                                if r2 < rs * rs {
                                    row.push((r2, j as u32, code_of(img).unwrap_or(u16::MAX)));
                                }
                            }
                        }
                    }
                }
                row.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)).then(a.2.cmp(&b.2)));
                row.into_iter().map(|(_, j, c)| (j, c)).collect()
            })
            .collect()
    }

    #[test]
    fn rows_are_every_pair_in_range_in_distance_order() {
        // A small cube (several images per axis) and a longer box, atoms scattered.
        for (l, n) in [([7.0, 7.0, 7.0], 20), ([14.0, 9.0, 11.0], 90)] {
            let x: Vec<[f64; 3]> =
                (0..n).map(|k| std::array::from_fn(|d| ((k * 7 + d * 3) as f64 * 0.618_033_988_75).fract() * l[d])).collect();
            let mut list = NeighborList::default();
            build(&x, [0.0; 3], l, 6.5, &mut list);
            let want = brute(&x, l, 6.5, &list);
            for i in 0..n {
                let r = list.start[i] as usize..list.start[i + 1] as usize;
                let got: Vec<(u32, u16)> = list.j[r.clone()].iter().copied().zip(list.code[r].iter().copied()).collect();
                assert_eq!(got, want[i], "row {i} of a {l:?} box");
            }
        }
    }
}
