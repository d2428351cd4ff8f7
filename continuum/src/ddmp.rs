//! The dual domain material point method (Dhakal Ch. 3.3 and 4.3; Zhang et al. 2011).
//!
//! The modified gradient (3.31) of node i's shape function at x is
//!   G_i(x) = alpha(x) grad S_i(x) + (1 - alpha(x)) sum_j S_j(x) / V_j * B_ji,
//! with V_j = int S_j dV and B_ji = int S_j grad S_i dV.
//!
//! Choice of quadrature (derived, and checked on the shock tubes): by default V_j = int S_j dV
//! is the exact integral over the grid (h per axis, h/2 at a non-periodic end node); the
//! alternative [`crate::Simulation::ddmp_point_volumes`] sums it over the step's integration
//! points, V_j = sum_s V_s S_j(x_s), which is 10-20 % more accurate on the weak tube but lets
//! the 2 x 16 strong tube open a tension gap at the contact (stopped by the guard at step
//! 201), so it is not the default. B_ji is the exact integral over the grid, a
//! fixed geometric stencil (products of 1D integrals: int S_j S_i' dx = +-1/2, and
//! int S_j S_i dx = h/6, 2h/3, or h/3 at a non-periodic end node). Summing B over the points
//! as well would make B_ji / V_j invariant under compression (numerator and denominator both
//! scale with V_p), so with V_p sigma_p constant (isothermal gas) the force would not respond
//! to compression at all: the MPM failure of Ch. 4.1 (measured: weak-tube L1 0.77 instead of
//! 0.03). Because B covers the whole grid, empty nodes next to a free surface receive force;
//! the solver hands it on to massive nodes with (7.4). sum_i B_ji = 0 exactly, so momentum is
//! conserved. A point's gradient is the sub-point-volume-weighted average (4.6) of G_i over
//! its sub-points; the same gradient gives the velocity gradient (4.10), so stress power and
//! kinetic energy change match.
//! (Measured on the weak tube with linear viscosity, L1 at 8/16/32/64 particles per cell:
//! 0.0309/-/0.0136/- with the exact V_j (the prototype: 0.031/0.021/0.0135/0.0116);
//! 0.0275/0.0170/0.0124/0.0119 with V_j summed over the points.)
//!
//! Consequence at a contact that starts on a node (the shock tube's partition): alpha = 0 on
//! the cell faces and the B term is continuous, so the strain rate sum_i v_i G_i is continuous
//! across the node and the points on either side keep their initial pressure ratio (unit test
//! below; measured and discussed in continuum/README.md). This is the scheme as specified, not
//! a quadrature error: points given the hat gradient's jump instead equilibrate but cross cells
//! noisily.
//!
//! Costs per step: one scatter of V_j (2^D values per integration point) and one pass building
//! every point's row from its sub-points (2^D x 3^D x D products per sub-point).

use crate::grid::Grid;
use crate::par::{self, Scatter};
use crate::particles::Particles;
use crate::shape::{Block, OutsideGrid, StencilPart, cell_node, cell_shape, node_index};

/// Number of neighbour offsets of a node within one cell (3^D).
pub const fn neighbours(d: usize) -> usize {
    3usize.pow(d as u32)
}

/// 1D integrals between node `j` (index along `axis`) and its neighbour `j + d`, d in -1..=1:
/// (int S_j S_{j+d}' dx, int S_j S_{j+d} dx), zero when the neighbour does not exist.
#[inline]
fn axis_integrals<const D: usize>(grid: &Grid<D>, axis: usize, j: i64, d: i64) -> (f64, f64) {
    let h = grid.h[axis];
    if grid.periodic(axis) {
        return match d {
            0 => (0.0, 2.0 * h / 3.0),
            1 => (0.5, h / 6.0),
            _ => (-0.5, h / 6.0),
        };
    }
    let last = grid.cells[axis] as i64;
    if j + d < 0 || j + d > last {
        return (0.0, 0.0);
    }
    match d {
        0 if j == 0 => (-0.5, h / 3.0),
        0 if j == last => (0.5, h / 3.0),
        0 => (0.0, 2.0 * h / 3.0),
        1 => (0.5, h / 6.0),
        _ => (-0.5, h / 6.0),
    }
}

/// int S_j dV over the grid.
fn exact_volume<const D: usize>(grid: &Grid<D>, j: &[usize; D]) -> f64 {
    (0..D).map(|a| if grid.periodic(a) || (j[a] > 0 && j[a] < grid.cells[a]) { grid.h[a] } else { 0.5 * grid.h[a] }).product()
}

/// B_ji = int S_j grad S_i dV over the grid for i = j + d, component by component:
/// B[b] = K_b prod_{a != b} M_a, from node j's per-axis tables `t[a][d + 1]` of
/// [`axis_integrals`] (K, M).
#[inline]
fn b_from_axes<const D: usize>(t: &[[(f64, f64); 3]; D], d: &[i64; D]) -> [f64; D] {
    std::array::from_fn(|b| {
        let mut v = t[b][(d[b] + 1) as usize].0;
        for (a, ta) in t.iter().enumerate() {
            if a != b {
                v *= ta[(d[a] + 1) as usize].1;
            }
        }
        v
    })
}

/// alpha of (3.27): 0.5 (prod_k n_c S_k)^(3 / (2 (n_c - 1) d)) over the n_c = 2^d nodes of the
/// cell. It is 0.5 at a cell centre and 0 on the cell's faces. (In 2D and 3D the printed
/// exponent gives per-axis exponents 1/2 and 2/7 instead of 1D's 3/2; any continuous alpha
/// vanishing on the faces keeps (3.31) continuous, so the printed form is kept.)
#[inline]
pub fn alpha<const D: usize>(s: &[f64; 8]) -> f64 {
    let nc = 1usize << D;
    let mut prod = 1.0;
    for &v in &s[..nc] {
        prod *= nc as f64 * v.max(0.0);
    }
    0.5 * match D {
        1 => prod * prod.sqrt(),
        2 => prod.sqrt().sqrt(),
        _ => prod.powf(3.0 / (2.0 * (nc as f64 - 1.0) * D as f64)),
    }
}

/// Sub-points per axis for `n` sub-points in `D` dimensions: n's prime factors dealt out,
/// largest first, to the axis with the fewest so far (8 in 2D gives 4 x 2, 16 in 2D 4 x 4).
pub fn sub_point_layout<const D: usize>(n: usize) -> [usize; D] {
    let mut factors = Vec::new();
    let mut m = n.max(1);
    let mut f = 2;
    while m > 1 {
        while m.is_multiple_of(f) {
            factors.push(f);
            m /= f;
        }
        f += 1;
    }
    factors.sort_unstable_by(|a, b| b.cmp(a));
    let mut per = [1usize; D];
    for f in factors {
        let a = (0..D).min_by_key(|&a| (per[a], a)).unwrap_or(0);
        per[a] *= f;
    }
    per
}

/// Places point `p`'s `n` sub-points evenly in its current domain, the parallelepiped
/// x_p + sum_a xi_a (F r0_a) with xi_a at the centres of equal sub-intervals of [-1, 1]
/// (in 1D [x - l F_xx, x + l F_xx]). They share the point's volume equally (4.6).
pub fn place_sub_points<const D: usize>(pts: &Particles<D>, p: usize, layout: &[usize; D], out: &mut [[f64; D]]) {
    if out.len() == 1 {
        out[0] = pts.x[p];
        return;
    }
    let r: [[f64; D]; D] = std::array::from_fn(|a| pts.half_vector(p, a));
    for (s, xs) in out.iter_mut().enumerate() {
        let mut rem = s;
        let mut x = pts.x[p];
        for a in 0..D {
            let k = rem % layout[a];
            rem /= layout[a];
            let xi = -1.0 + (2 * k + 1) as f64 / layout[a] as f64;
            for i in 0..D {
                x[i] += xi * r[a][i];
            }
        }
        *xs = x;
    }
}

/// Node window (linear indices) of the cells holding a chunk's sub-points.
fn sub_point_span<const D: usize>(grid: &Grid<D>, subs: &[[f64; D]]) -> (usize, usize) {
    let (mut lo, mut hi) = (usize::MAX, 0);
    for x in subs {
        let sh = cell_shape(grid, x);
        for k in [0, (1usize << D) - 1] {
            if let Some(n) = node_index(grid, &cell_node(&sh.cell, k)) {
                lo = lo.min(n);
                hi = hi.max(n + 1);
            }
        }
    }
    if lo > hi {
        return (0, 0);
    }
    // A periodic wrap can put the cell's last node below its first: take the whole grid.
    if subs.iter().any(|x| {
        let sh = cell_shape(grid, x);
        let a = node_index(grid, &cell_node(&sh.cell, 0));
        let b = node_index(grid, &cell_node(&sh.cell, (1usize << D) - 1));
        matches!((a, b), (Some(a), Some(b)) if b < a)
    }) {
        return (0, grid.node_count());
    }
    (lo, hi)
}

/// Scatters V_j = sum_s V_s S_j(x_s) from the integration points (`subs`, `n` per point, each
/// carrying 1/n of its point's current volume) into `volume` (one value per node).
pub fn assemble_volumes<const D: usize>(
    grid: &Grid<D>,
    pts: &Particles<D>,
    subs: &[[f64; D]],
    n: usize,
    tiles: &par::Tiles,
    scatter: &mut Scatter,
    volume: &mut Vec<f64>,
) {
    let nc = 1usize << D;
    scatter.run_tiled(
        tiles,
        grid.node_count(),
        1,
        volume,
        |p| sub_point_span(grid, &subs[p * n..(p + 1) * n]),
        |tile, w| {
            for &p in tile {
                let vs = pts.volume[p] / n as f64;
                for x in &subs[p * n..(p + 1) * n] {
                    let sh = cell_shape(grid, x);
                    for j in 0..nc {
                        if let Some(jl) = node_index(grid, &cell_node(&sh.cell, j)) {
                            w.slot(jl)[0] += vs * sh.s[j];
                        }
                    }
                }
            }
        },
    );
}

/// Appends point `p`'s DDMP row: hat weights at x_p and the sub-point average of (3.31).
pub(crate) fn ddmp_row<const D: usize>(
    grid: &Grid<D>,
    pts: &Particles<D>,
    p: usize,
    subs: &[[f64; D]],
    volume: Option<&[f64]>,
    block: &mut Block<D>,
    out: &mut StencilPart<D>,
) -> Result<(), OutsideGrid> {
    let nc = 1usize << D;
    let nn = neighbours(D);
    // Points outside the grid are an error, not clamped.
    for a in 0..D {
        let x = pts.x[p][a];
        let inside = grid.periodic(a) || (x >= grid.origin[a] && x <= grid.extent_max()[a]);
        if !inside || !x.is_finite() {
            return Err(OutsideGrid { point: p, axis: a, position: x, inverted: false });
        }
    }
    let own = cell_shape(grid, &pts.x[p]);
    let (mut lo, mut hi) = (own.cell, own.cell);
    for x in subs {
        let sh = cell_shape(grid, x);
        for a in 0..D {
            lo[a] = lo[a].min(sh.cell[a]);
            hi[a] = hi[a].max(sh.cell[a]);
        }
    }
    block.reset(std::array::from_fn(|a| lo[a] - 1), std::array::from_fn(|a| hi[a] + 2));
    // Two passes: the alpha-weighted hat gradients and, per node j, the coefficient
    // c_j = sum_s (1 - alpha_s) S_j(x_s) / (n V_j); then c_j B_ji once per node j rather than
    // once per (sub-point, node) pair (a point's sub-points share few nodes).
    let inv_n = 1.0 / subs.len() as f64;
    for x in subs {
        let sh = cell_shape(grid, x);
        let al = alpha::<D>(&sh.s);
        for j in 0..nc {
            let bj = block.index(&cell_node(&sh.cell, j));
            for d in 0..D {
                block.g[bj][d] += al * inv_n * sh.g[j][d];
            }
            block.c[bj] += (1.0 - al) * sh.s[j];
        }
    }
    for bj in 0..block.c.len() {
        let c = block.c[bj];
        if c == 0.0 {
            continue;
        }
        let jn = block.node(bj);
        let Some(jl) = node_index(grid, &jn) else { continue };
        let jw = grid.unlinear(jl);
        let vj = match volume {
            Some(v) => v[jl],
            None => exact_volume(grid, &jw),
        };
        if !(vj > 0.0) {
            continue;
        }
        let coef = c * inv_n / vj;
        // The 1D integrals of node j with its neighbours, per axis (3 D values for 3^D offsets).
        let t: [[(f64, f64); 3]; D] = std::array::from_fn(|a| std::array::from_fn(|k| axis_integrals(grid, a, jw[a] as i64, k as i64 - 1)));
        for o in 0..nn {
            let mut rem = o;
            let di: [i64; D] = std::array::from_fn(|_| {
                let d = (rem % 3) as i64 - 1;
                rem /= 3;
                d
            });
            let b = b_from_axes(&t, &di);
            if b.iter().all(|v| *v == 0.0) {
                continue;
            }
            let i: [i64; D] = std::array::from_fn(|a| jn[a] + di[a]);
            let bi = block.index(&i);
            for d in 0..D {
                block.g[bi][d] += coef * b[d];
            }
        }
    }
    for k in 0..nc {
        let b = block.index(&cell_node(&own.cell, k));
        block.w[b] += own.s[k];
    }
    block.emit(grid, p, &pts.x[p], out)
}

/// Sub-point positions of every point (`n` per point), chunk-parallel; with `owned` non-empty,
/// of the points it marks only (the others keep what they held).
pub fn place_all<const D: usize>(pts: &Particles<D>, n: usize, owned: &[bool], out: &mut Vec<[f64; D]>) {
    let layout = sub_point_layout::<D>(n);
    out.resize(pts.len() * n, [0.0; D]);
    par::for_chunks_mut(out, n, |r, s| {
        for (k, p) in r.enumerate() {
            if !owned.is_empty() && !owned[p] {
                continue;
            }
            place_sub_points(pts, p, &layout, &mut s[k * n..(k + 1) * n]);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn alpha_is_half_at_centre_and_zero_on_faces() {
        let g1 = Grid::<1> { origin: [0.0], h: [1.0], cells: [4], faces: [(crate::Face::Free, crate::Face::Free)] };
        assert!((alpha::<1>(&cell_shape(&g1, &[1.5]).s) - 0.5).abs() < 1e-15);
        assert_eq!(alpha::<1>(&cell_shape(&g1, &[2.0]).s), 0.0);
        let f = || (crate::Face::Free, crate::Face::Free);
        let g2 = Grid::<2> { origin: [0.0; 2], h: [1.0; 2], cells: [4; 2], faces: [f(), f()] };
        assert!((alpha::<2>(&cell_shape(&g2, &[1.5, 2.5]).s) - 0.5).abs() < 1e-15);
        assert_eq!(alpha::<2>(&cell_shape(&g2, &[1.5, 2.0]).s), 0.0);
        let g3 = Grid::<3> { origin: [0.0; 3], h: [1.0; 3], cells: [4; 3], faces: [f(), f(), f()] };
        assert!((alpha::<3>(&cell_shape(&g3, &[1.5, 2.5, 0.5]).s) - 0.5).abs() < 1e-14);
    }

    /// The root cause of the shock tube's contact (continuum/README.md): for a nodal velocity
    /// with a kink at node 4 (v_4 = 1, every other node 0), the strain rate sum_i v_i G_i(x)
    /// of (3.31) is continuous across the node (alpha = 0 on the faces; the B term is a hat
    /// interpolation of nodal averages), while the hat gradient jumps by 2/h there. Points
    /// just left and right of a node therefore share one strain history under DDMP.
    #[test]
    fn the_modified_gradient_is_continuous_across_a_node() {
        let grid = Grid::<1> { origin: [0.0], h: [1.0], cells: [8], faces: [(crate::Face::Free, crate::Face::Free)] };
        let rate = |x: f64| {
            let mut pts = Particles::<1>::default();
            pts.push(0, [x], [0.0], 1.0, 1.0 / 64.0, [1.0 / 128.0], Particles::<1>::identity());
            let mut part = StencilPart::default();
            part.clear(0);
            ddmp_row(&grid, &pts, 0, &[[x]], None, &mut Block::default(), &mut part).expect("row");
            part.end_point();
            let st = crate::shape::Stencil { parts: vec![part] };
            let (nodes, _, grads) = st.row(0);
            nodes.iter().zip(grads).filter(|(i, _)| **i == 4).map(|(_, g)| g[0]).sum::<f64>()
        };
        let eps = 1.0 / 128.0;
        let (left, right) = (rate(4.0 - eps), rate(4.0 + eps));
        // The hat gradient would give +1 and -1: a jump of 2.
        assert!((left - right).abs() < 0.05, "DDMP strain rate jumps across the node: {left} vs {right}");
        // Inside a cell alpha > 0 and the rate differs from the node value.
        let centre = rate(3.5);
        assert!(centre > left + 0.1, "centre {centre} vs next to the node {left}");
    }

    #[test]
    fn layouts_multiply_to_n() {
        assert_eq!(sub_point_layout::<1>(16), [16]);
        assert_eq!(sub_point_layout::<2>(8), [4, 2]);
        assert_eq!(sub_point_layout::<2>(16), [4, 4]);
        assert_eq!(sub_point_layout::<3>(8), [2, 2, 2]);
        assert_eq!(sub_point_layout::<2>(1), [1, 1]);
    }
}
