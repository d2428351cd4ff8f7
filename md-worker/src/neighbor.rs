//! Half neighbour lists with explicit periodic images.
//!
//! A pair is stored once as (i, j, n): atom j's image at `x_j + n * L` lies within
//! `cutoff + skin` of atom i. A box shorter than twice the cut-off simply has several
//! entries for the same j with different n, so forces stay exact for any box size.
//! Images are integers, so the list stays valid while the box is stretched.

use serde::{Deserialize, Serialize};

/// Neighbour list of one box, CSR layout (`start[i]..start[i+1]` indexes `j` and `image`).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct NeighborList {
    /// Row starts, length n_atoms + 1.
    pub start: Vec<u32>,
    /// Neighbour atom (box-local index).
    pub j: Vec<u32>,
    /// Image of the neighbour.
    pub image: Vec<[i32; 3]>,
}

/// Build the half list of atoms at `x` (already wrapped into `[lo, lo + l)`) with radius `rs`.
/// Pairs come out in a fixed order (cells, then atom index), so the same input gives the
/// same list.
pub fn build(x: &[[f64; 3]], lo: [f64; 3], l: [f64; 3], rs: f64, list: &mut NeighborList) {
    let n = x.len();
    let mut nc = [1usize; 3];
    let mut reach = [1i32; 3];
    for d in 0..3 {
        nc[d] = ((l[d] / rs).floor() as usize).max(1);
        let cell = l[d] / nc[d] as f64;
        reach[d] = (rs / cell).ceil() as i32;
    }
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
    let rs2 = rs * rs;
    list.start.clear();
    list.j.clear();
    list.image.clear();
    list.start.push(0);
    for i in 0..n {
        let ci = cells[i];
        for ox in -reach[0]..=reach[0] {
            for oy in -reach[1]..=reach[1] {
                for oz in -reach[2]..=reach[2] {
                    let o = [ox, oy, oz];
                    let mut cw = [0usize; 3];
                    let mut img = [0i32; 3];
                    for d in 0..3 {
                        let c = ci[d] as i32 + o[d];
                        cw[d] = c.rem_euclid(nc[d] as i32) as usize;
                        img[d] = c.div_euclid(nc[d] as i32);
                    }
                    let f = flat(cw);
                    for &j in &order[count[f] as usize..count[f + 1] as usize] {
                        let j = j as usize;
                        let keep = j > i || (j == i && img > [0, 0, 0]);
                        if !keep {
                            continue;
                        }
                        let mut r2 = 0.0;
                        for d in 0..3 {
                            let dx = x[j][d] + img[d] as f64 * l[d] - x[i][d];
                            r2 += dx * dx;
                        }
                        if r2 < rs2 {
                            list.j.push(j as u32);
                            list.image.push(img);
                        }
                    }
                }
            }
        }
        list.start.push(list.j.len() as u32);
    }
}
