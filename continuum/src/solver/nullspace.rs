//! Nullspace filters on the point velocity gradient (battery thesis B 4.50-4.92; notes A.5),
//! `scheme.nullspace_filter = "none" | "local" | "global-svd"`.
//!
//! The point-to-node map S*_ip = phi_ip / W_i (W_i = sum_p phi_ip, 4.17) has more columns
//! (points) than rows (nodes): a point field u with sum_p S*_ip u_p = 0 at every node (a
//! zig-zag between the points of a cell, say) is invisible to the grid. The gradient the points
//! get from the nodes, g_p = sum_i v_i grad phi_i(x_p), is not in the row space of S* in general
//! (its node-to-point interpolation can put a null component back: 4.66-4.72), and that
//! component is the particle noise the filters remove.
//!
//! - `local` (4.74-4.83, [124]): one more particle -> node -> particle cycle on the gradient,
//!   g^F_p = sum_i phi_ip G_i with G_i = sum_q S*_iq g_q. The notes' erratum is used: (4.80)
//!   weights node i by (1 - alpha_p) although (4.33)-(4.34) define alpha_p as node i's own
//!   weight, so the weight here is phi_i(x_p) itself. A component with sum_q S*_iq g_q = 0 at
//!   every node is removed exactly; a constant gradient is kept exactly (sum_q S*_iq = 1 and
//!   sum_i phi_ip = 1); a linear one is kept where the weighted centroid sum_q S*_iq x_q of
//!   node i's points is X_i (symmetric points: uniform interior points), and moved by
//!   O(h) times its slope elsewhere (boundary nodes, irregular points). It widens the stencil and
//!   does not raise the order (4.83). Every component of the D x D block of L is filtered alike,
//!   so it is the same code in 1D, 2D and 3D (4.4.1: "no conceptual problem"); the components
//!   outside the block are left alone. The node sums run through the solver's tiled scatter, so
//!   the result is bitwise the same for any thread count.
//! - `global-svd` (4.73, [124]): the orthogonal projection of the 1D gradient vector (all points
//!   at once) onto the row space of the (nodes with points) x (points) matrix S*,
//!   g^F = V_r V_r^T g with V_r the right singular vectors of singular values above
//!   max(rows, points) eps sigma_max (the numerical-rank cut of LAPACK/numpy; chosen here, the
//!   thesis names none). The row space is that of the plain phi_ip rows; the rows are scaled by
//!   1/W_i as printed, which only matters to the rank cut. O(points^3) each step: 1D reference
//!   runs only (the validator refuses it in 2D/3D and above [`SVD_MAX_POINTS`] points).
//!
//! Both apply to the gradient after it is computed (steps 7-8 read the filtered L: the
//! deformation gradient, the volume and the stress), in every explicit integrator; the point
//! velocities and positions are not filtered (the thesis filters "the velocity gradient
//! calculation", 4.4).

use super::*;

/// Which nullspace filter the velocity gradient gets (`scheme.nullspace_filter`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum NullspaceFilter {
    /// The gradient as computed.
    #[default]
    None,
    /// One extra particle -> node -> particle cycle (B 4.74-4.83), any dimension.
    Local,
    /// Projection onto the row space of S* by an SVD of the whole map (B 4.73), 1D only.
    GlobalSvd,
}

/// Most points the global SVD filter takes (one dense SVD of nodes x points per step).
pub const SVD_MAX_POINTS: usize = 2000;

/// The local filter on the D x D block of `values` (one tensor per point, in point order):
/// values_p <- sum_i phi_ip (sum_q phi_iq values_q / sum_q phi_iq) over the stencil's weights.
pub fn local_filter<const D: usize>(
    n_nodes: usize,
    stencil: &Stencil<D>,
    tiles: &par::Tiles,
    scatter: &mut Scatter,
    flat: &mut Vec<f64>,
    values: &mut [Mat3],
) {
    let stride = 1 + D * D;
    {
        let vals: &[Mat3] = values;
        scatter.run_tiled(
            tiles,
            n_nodes,
            stride,
            flat,
            |p| row_span(stencil, p),
            |tile, w| {
                for &p in tile {
                    let (nodes, weights, _) = stencil.row(p);
                    for (&i, &s) in nodes.iter().zip(weights) {
                        if s == 0.0 {
                            continue;
                        }
                        let slot = w.slot(i);
                        slot[0] += s;
                        for a in 0..D {
                            for b in 0..D {
                                slot[1 + a * D + b] += s * vals[p][a][b];
                            }
                        }
                    }
                }
            },
        );
    }
    // G_i = sum_q S*_iq g_q (nodes without points: none of their weight reaches a point).
    flat.par_chunks_mut(stride).for_each(|f| {
        if f[0] > 0.0 {
            let w = f[0];
            for v in &mut f[1..] {
                *v /= w;
            }
        }
    });
    let g: &[f64] = flat;
    par::for_chunks_mut(values, 1, |r, out| {
        for (k, p) in r.enumerate() {
            let (nodes, weights, _) = stencil.row(p);
            let mut l = [[0.0; D]; D];
            for (&i, &s) in nodes.iter().zip(weights) {
                if s == 0.0 {
                    continue;
                }
                let gi = &g[i * stride + 1..(i + 1) * stride];
                for a in 0..D {
                    for b in 0..D {
                        l[a][b] += s * gi[a * D + b];
                    }
                }
            }
            for a in 0..D {
                for b in 0..D {
                    out[k][a][b] = l[a][b];
                }
            }
        }
    });
}

/// The global SVD filter on the 1D values u_p (`values[p][0][0]`): u <- V_r V_r^T u over the
/// right singular vectors of S* (see the module notes). Errors say why it cannot run.
pub fn global_svd_filter<const D: usize>(n_nodes: usize, stencil: &Stencil<D>, values: &mut [Mat3]) -> Result<(), String> {
    if D != 1 {
        return Err(format!("the global SVD filter is 1D only (this run is {D}D)"));
    }
    let n = values.len();
    if n > SVD_MAX_POINTS {
        return Err(format!("the global SVD filter takes at most {SVD_MAX_POINTS} points (this run has {n})"));
    }
    // Rows: the nodes that carry weight, in node order.
    let mut w = vec![0.0; n_nodes];
    for p in 0..n {
        let (nodes, weights, _) = stencil.row(p);
        for (&i, &s) in nodes.iter().zip(weights) {
            w[i] += s;
        }
    }
    let mut row_of = vec![usize::MAX; n_nodes];
    let mut rows = 0;
    for i in 0..n_nodes {
        if w[i] > 0.0 {
            row_of[i] = rows;
            rows += 1;
        }
    }
    if rows == 0 || n == 0 {
        return Ok(());
    }
    let mut s = nalgebra::DMatrix::<f64>::zeros(rows, n);
    for p in 0..n {
        let (nodes, weights, _) = stencil.row(p);
        for (&i, &phi) in nodes.iter().zip(weights) {
            if phi != 0.0 {
                s[(row_of[i], p)] += phi / w[i];
            }
        }
    }
    let svd = s.svd(false, true);
    let vt = svd.v_t.ok_or("the SVD of the point-to-node map returned no right singular vectors")?;
    let sigma = &svd.singular_values;
    let top = sigma.iter().cloned().fold(0.0, f64::max);
    if !top.is_finite() {
        return Err("the point-to-node map has a non-finite singular value".into());
    }
    let cut = rows.max(n) as f64 * f64::EPSILON * top;
    let u: Vec<f64> = values.iter().map(|l| l[0][0]).collect();
    let mut out = vec![0.0; n];
    for k in 0..sigma.len() {
        if !(sigma[k] > cut) {
            continue;
        }
        let row = vt.row(k);
        let c: f64 = (0..n).map(|p| row[p] * u[p]).sum();
        for p in 0..n {
            out[p] += c * row[p];
        }
    }
    for (l, v) in values.iter_mut().zip(out) {
        l[0][0] = v;
    }
    Ok(())
}

impl<const D: usize> Simulation<D> {
    /// Applies the scene's nullspace filter to the point velocity gradients just computed.
    pub(super) fn filter_velocity_gradients(&mut self, step: u64) -> Result<(), SolverError> {
        match self.nullspace_filter {
            NullspaceFilter::None => Ok(()),
            NullspaceFilter::Local => {
                let n = self.grid.node_count();
                local_filter(n, &self.stencil, &self.tiles, &mut self.scatter, &mut self.flat, &mut self.points.vel_grad);
                Ok(())
            }
            NullspaceFilter::GlobalSvd => {
                global_svd_filter(self.grid.node_count(), &self.stencil, &mut self.points.vel_grad).map_err(|what| SolverError::Diverged {
                    step,
                    what,
                    cause: "the global SVD filter is for small 1D reference runs: use nullspace_filter = \"local\"",
                })
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Face;

    /// Hat-function (tensor-product) rows of points on `cells` cells of width h from the origin.
    fn hat_stencil<const D: usize>(h: f64, cells: usize, x: &[[f64; D]]) -> (Grid<D>, Stencil<D>, par::Tiles) {
        let grid = Grid { origin: [0.0; D], h: [h; D], cells: [cells; D], faces: std::array::from_fn(|_| (Face::Free, Face::Free)) };
        let mut parts = Vec::new();
        for (c, chunk) in x.chunks(CHUNK).enumerate() {
            let mut part = StencilPart::default();
            part.clear(c * CHUNK);
            for xp in chunk {
                let cell: [usize; D] = std::array::from_fn(|a| ((xp[a] / h).floor() as usize).min(cells - 1));
                let t: [f64; D] = std::array::from_fn(|a| xp[a] / h - cell[a] as f64);
                for corner in 0..1usize << D {
                    let mut idx = [0usize; D];
                    let mut s = 1.0;
                    for a in 0..D {
                        let up = (corner >> a) & 1 == 1;
                        idx[a] = cell[a] + up as usize;
                        s *= if up { t[a] } else { 1.0 - t[a] };
                    }
                    let g: [f64; D] = std::array::from_fn(|b| {
                        let mut v = 1.0;
                        for a in 0..D {
                            let up = (corner >> a) & 1 == 1;
                            v *= if a == b {
                                if up { 1.0 / h } else { -1.0 / h }
                            } else if up {
                                t[a]
                            } else {
                                1.0 - t[a]
                            };
                        }
                        v
                    });
                    part.push(grid.linear(idx), s, g);
                }
                part.end_point();
            }
            parts.push(part);
        }
        let mut tiles = par::Tiles::default();
        tiles.assign(par::slab_tile_count(&grid), x.len(), |p| par::slab_tile(&grid, &x[p]));
        (grid, Stencil { parts }, tiles)
    }

    /// `ppc` points per cell and axis at the cell-centred positions (k + 1/2) h / ppc.
    fn uniform<const D: usize>(h: f64, cells: usize, ppc: usize) -> Vec<[f64; D]> {
        let per = cells * ppc;
        (0..per.pow(D as u32))
            .map(|k| {
                let mut r = k;
                std::array::from_fn(|_| {
                    let j = r % per;
                    r /= per;
                    (j as f64 + 0.5) * h / ppc as f64
                })
            })
            .collect()
    }

    fn run_local<const D: usize>(h: f64, cells: usize, x: &[[f64; D]], l: impl Fn(&[f64; D]) -> Mat3) -> (Vec<Mat3>, Vec<Mat3>) {
        let (grid, st, tiles) = hat_stencil(h, cells, x);
        let before: Vec<Mat3> = x.iter().map(&l).collect();
        let mut after = before.clone();
        local_filter(grid.node_count(), &st, &tiles, &mut Scatter::default(), &mut Vec::new(), &mut after);
        (before, after)
    }

    /// sum_q S*_iq u_q at every node (the grid's view of a point field).
    fn nodal<const D: usize>(h: f64, cells: usize, x: &[[f64; D]], u: &[f64]) -> Vec<f64> {
        let (grid, st, _) = hat_stencil(h, cells, x);
        let (mut w, mut s) = (vec![0.0; grid.node_count()], vec![0.0; grid.node_count()]);
        for p in 0..x.len() {
            let (nodes, weights, _) = st.row(p);
            for (&i, &phi) in nodes.iter().zip(weights) {
                w[i] += phi;
                s[i] += phi * u[p];
            }
        }
        s.iter().zip(&w).map(|(s, w)| if *w > 0.0 { s / w } else { 0.0 }).collect()
    }

    fn diag(v: f64) -> Mat3 {
        let mut m = tensor::ZERO;
        m[0][0] = v;
        m
    }

    /// The null mode of 2 points per cell (hat weights 3/4, 1/4): (1, -3, 3, -1) over every pair
    /// of cells (node sums 3/4 - 3/4, 1/4 - 9/4 + 9/4 - 1/4, -3/4 + 3/4), the analogue of the
    /// thesis's u0 + u1 - u2 - u3 = 0 (4.72). `k` is the point's index along the axis.
    fn null_mode(k: usize) -> f64 {
        [1.0, -3.0, 3.0, -1.0][k % 4]
    }

    #[test]
    fn the_1d_null_mode_is_invisible_to_the_grid_and_the_local_filter_removes_it() {
        let (h, cells) = (0.1, 10);
        let x = uniform::<1>(h, cells, 2);
        let z: Vec<f64> = (0..x.len()).map(null_mode).collect();
        for (i, v) in nodal(h, cells, &x, &z).iter().enumerate() {
            assert!(v.abs() < 1e-13, "node {i} sees the mode: {v}");
        }
        // Planted on a smooth gradient: the filter takes it out and leaves the smooth part.
        let smooth = |x: &[f64; 1]| 0.3 + 2.0 * x[0] + (5.0 * x[0]).sin();
        let k = |x: &[f64; 1]| (x[0] / h * 2.0) as usize;
        let (before, after) = run_local(h, cells, &x, |xp| diag(smooth(xp) + 0.5 * null_mode(k(xp))));
        let (_, clean) = run_local(h, cells, &x, |xp| diag(smooth(xp)));
        for p in 0..x.len() {
            assert!((before[p][0][0] - smooth(&x[p])).abs() >= 0.5, "the mode is planted at point {p}");
            assert!((after[p][0][0] - clean[p][0][0]).abs() < 1e-14, "point {p}: {} vs {}", after[p][0][0], clean[p][0][0]);
        }
        // Away from the ends a linear gradient passes the filter unchanged.
        let (_, lin) = run_local(h, cells, &x, |xp| diag(0.3 + 2.0 * xp[0]));
        for p in 2..x.len() - 2 {
            assert!((lin[p][0][0] - 0.3 - 2.0 * x[p][0]).abs() < 1e-14, "point {p}: {}", lin[p][0][0]);
        }
    }

    #[test]
    fn the_local_filter_keeps_constants_everywhere_and_linear_fields_on_symmetric_interior_points() {
        let (h, cells) = (0.1, 10);
        // 1D, irregular points: a constant survives to round-off.
        let x: Vec<[f64; 1]> =
            (0..3 * cells).map(|k| [h * ((k / 3) as f64 + [0.13, 0.47, 0.81][k % 3] + 0.04 * (((k * 7) % 5) as f64 - 2.0))]).collect();
        let (_, after) = run_local(h, cells, &x, |_| diag(-4.25));
        for (p, l) in after.iter().enumerate() {
            assert!((l[0][0] + 4.25).abs() < 1e-14, "1D constant, point {p}: {}", l[0][0]);
        }
        // 2D, uniform 2 x 2 points per cell: a linear L is kept exactly at points whose
        // nodes are all interior (the centroid of each node's points is the node).
        let x = uniform::<2>(h, cells, 2);
        let lin = |x: &[f64; 2]| -> Mat3 { [[1.0 + x[0], 2.0 - 3.0 * x[1], 0.0], [0.5 * x[0] - x[1], -0.7, 0.0], [0.0, 0.0, 0.0]] };
        let (_, after) = run_local(h, cells, &x, lin);
        let mut checked = 0;
        for p in 0..x.len() {
            let interior = x[p].iter().all(|&v| v > h && v < h * (cells - 1) as f64);
            let want = lin(&x[p]);
            let err =
                (0..2).flat_map(|a| (0..2).map(move |b| (a, b))).map(|(a, b)| (after[p][a][b] - want[a][b]).abs()).fold(0.0, f64::max);
            if interior {
                checked += 1;
                assert!(err < 1e-13, "2D linear, point {p} at {:?}: error {err}", x[p]);
            } else {
                // Boundary nodes see their points on one side only: the centroid is off the node.
                assert!(err < 3.0 * h, "2D linear near the boundary, point {p}: error {err}");
            }
        }
        assert!(checked > 100);
    }

    #[test]
    fn the_local_filter_removes_a_2d_checkerboard() {
        let (h, cells) = (0.1, 8);
        let x = uniform::<2>(h, cells, 2);
        // The tensor product of the 1D null mode: a checkerboard of (1, -3, 3, -1) blocks.
        let sign = |x: &[f64; 2]| null_mode((x[0] / h * 2.0) as usize) * null_mode((x[1] / h * 2.0) as usize);
        let board: Vec<f64> = x.iter().map(sign).collect();
        for (i, v) in nodal(h, cells, &x, &board).iter().enumerate() {
            assert!(v.abs() < 1e-13, "node {i} sees the checkerboard: {v}");
        }
        let smooth = |_: &[f64; 2]| -> Mat3 { [[0.2, 1.5, 0.0], [-0.4, 0.9, 0.0], [0.0, 0.0, 0.0]] };
        let planted = |x: &[f64; 2]| -> Mat3 {
            let mut m = smooth(x);
            m[0][1] += 0.5 * sign(x);
            m[1][0] -= 2.0 * sign(x);
            m
        };
        let (_, after) = run_local(h, cells, &x, planted);
        for p in 0..x.len() {
            let want = smooth(&x[p]);
            for a in 0..2 {
                for b in 0..2 {
                    assert!((after[p][a][b] - want[a][b]).abs() < 1e-14, "point {p} L[{a}][{b}] = {}", after[p][a][b]);
                }
            }
        }
    }

    #[test]
    fn the_local_filter_gives_the_same_bits_for_any_thread_count() {
        let (h, cells) = (0.05, 40);
        let x = uniform::<2>(h, cells, 2);
        let l =
            |x: &[f64; 2]| -> Mat3 { [[(7.0 * x[0]).sin(), x[1] * x[1], 0.0], [x[0] * x[1], (3.0 * x[1]).cos(), 0.0], [0.0, 0.0, 0.0]] };
        let run = |threads| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("a pool");
            pool.install(|| run_local(h, cells, &x, l).1)
        };
        let one = run(1);
        for t in [2, 3] {
            let other = run(t);
            assert!(
                one.iter().zip(&other).all(|(a, b)| a.iter().flatten().zip(b.iter().flatten()).all(|(u, v)| u.to_bits() == v.to_bits())),
                "{t} threads"
            );
        }
    }

    #[test]
    fn the_global_svd_filter_projects_onto_the_row_space() {
        let (h, cells) = (0.1, 10);
        let x = uniform::<1>(h, cells, 2);
        let (grid, st, _) = hat_stencil(h, cells, &x);
        let smooth = |x: f64| (3.0 * x).sin();
        let zig = |p: usize| 0.7 * null_mode(p);
        let mut v: Vec<Mat3> = (0..x.len()).map(|p| diag(smooth(x[p][0]) + zig(p))).collect();
        global_svd_filter(grid.node_count(), &st, &mut v).unwrap();
        let u: Vec<f64> = v.iter().map(|l| l[0][0]).collect();
        // The null mode is orthogonal to every row, so it goes; the grid sees the same field.
        let mut clean: Vec<Mat3> = (0..x.len()).map(|p| diag(smooth(x[p][0]))).collect();
        global_svd_filter(grid.node_count(), &st, &mut clean).unwrap();
        for p in 0..x.len() {
            assert!((u[p] - clean[p][0][0]).abs() < 1e-12, "point {p}: {} vs {}", u[p], clean[p][0][0]);
        }
        let before: Vec<f64> = (0..x.len()).map(|p| smooth(x[p][0]) + zig(p)).collect();
        let (a, b) = (nodal(h, cells, &x, &before), nodal(h, cells, &x, &u));
        for i in 0..a.len() {
            assert!((a[i] - b[i]).abs() < 1e-12, "node {i}: the projection changed what the grid sees");
        }
        // A projection: applying it again changes nothing.
        let mut again = v.clone();
        global_svd_filter(grid.node_count(), &st, &mut again).unwrap();
        for p in 0..x.len() {
            assert!((again[p][0][0] - u[p]).abs() < 1e-12, "point {p}: not idempotent");
        }
        // 11 nodes, 20 points: the filtered field lies in an 11-dimensional space, so the
        // piecewise-linear interpolant of the nodes (in the row space) passes unchanged.
        let mut hat: Vec<Mat3> = (0..x.len()).map(|p| diag(1.0 - 2.0 * x[p][0])).collect();
        global_svd_filter(grid.node_count(), &st, &mut hat).unwrap();
        for p in 0..x.len() {
            assert!((hat[p][0][0] - (1.0 - 2.0 * x[p][0])).abs() < 1e-12, "point {p}: a linear field moved");
        }
    }

    #[test]
    fn the_global_svd_filter_refuses_2d_and_too_many_points() {
        let x = uniform::<2>(0.5, 2, 1);
        let (grid, st, _) = hat_stencil(0.5, 2, &x);
        let e = global_svd_filter(grid.node_count(), &st, &mut vec![tensor::ZERO; x.len()]).unwrap_err();
        assert!(e.contains("1D only"), "{e}");
        let x = uniform::<1>(1.0 / 1100.0, 1100, 2);
        let (grid, st, _) = hat_stencil(1.0 / 1100.0, 1100, &x);
        let e = global_svd_filter(grid.node_count(), &st, &mut vec![tensor::ZERO; x.len()]).unwrap_err();
        assert!(e.contains("at most 2000 points"), "{e}");
    }
}
