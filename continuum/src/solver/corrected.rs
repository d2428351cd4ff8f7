//! Corrected derivatives of the battery thesis's partition-of-unity mapping (B 4.14-4.29; notes
//! A.4 with its errata), as an option on the nodal force of the explicit schemes; 1D as in the
//! thesis, and in 2D/3D the RKPM-style extension the notes mark as proposed (see
//! [`correction_factors`]: the scalar k_i becomes the matrix A_i = -W_i M_i^-T).
//!
//! Derivation (recorded because the print has sign and scale errata). With the plain weights
//! phi_ip = phi_i(x_p), W_i = sum_p phi_ip, W'_i = sum_p phi'_ip and S*_ip = phi_ip / W_i:
//! - the thesis's DS**_ip = phi'_ip / W_i - phi_ip W'_i / W_i^2 is the derivative of S*_ip under a
//!   common shift of every point, i.e. minus its derivative in the node position X_i, so the
//!   constant-correct nodal derivative is D_i[y] = -sum_p DS**_ip y_p and
//!   the linear-correct one D_i[y] = sum_p DS*_ip y_p with DS* = C_i DS**,
//!   C_i = 1 / sum_p x_p DS**_ip (4.25-4.27; C_i = -1 on uniform interior points).
//! - The force with the erratum's sign, f_i = +sum_p DS*_ip sigma_p V_p with m_i = sum_p S*_ip m_p
//!   (4.39), gives the acceleration W_i sum_p DS*_ip sigma_p V_p / m_i^lump with the lumped mass
//!   m_i^lump = sum_p phi_ip m_p = W_i m_i, and the nodal velocity of (4.40) equals the lumped one.
//!   So the scheme is plain MPM (lumped mass, the usual f_i = -sum_p V_p sigma_p G_ip) with the
//!   force gradient G_ip replaced by G~_ip = -W_i DS*_ip:
//!   "constant": G~_ip = phi'_ip - phi_ip r_i, r_i = W'_i / W_i;
//!   "linear":   G~_ip = k_i (phi'_ip - phi_ip r_i), k_i = -W_i / sum_q (x_q - X_i)(phi'_iq - phi_iq r_i).
//!   Then sum_p G~_ip = 0 (a constant stress gives no force at any node) and, for "linear",
//!   sum_p (x_p - X_i) G~_ip = -W_i (a linear stress with equal point volumes V gives
//!   f_i = V W_i sigma', a_i = sigma' / rho exactly). On uniform interior points k_i = 1 and
//!   r_i = 0: the corrected force is MPM's there.
//! - What each reproduces (as the nodal derivative -sum_p G~_ip y_p / W_i): "constant" gives 0
//!   for a constant field on any point set, "linear" the exact slope of a linear field on any
//!   point set, and of a quadratic only where sum_p G~_ip (x_p - X_i)^2 = 0 (symmetric points).
//!
//! The velocity gradient stays the plain sum_i v_i phi'_i(x_p) (the thesis corrects the force).
//! Caveats (notes A.4): a free-surface node loses the traction-free condition (a constant
//! stress gives it no force), and sum_i f_i != 0, so momentum is not conserved (its drift is
//! not yet measured in tests/schemes.rs).

use super::*;

/// The gradient the nodal force uses (`scheme.gradient_correction`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GradientCorrection {
    /// The scheme's own shape-function gradients.
    #[default]
    None,
    /// Constant-correct: sum_p G~_ip = 0 at every node (B 4.23-4.24).
    Constant,
    /// Linear-correct: also sum_p (x_p - X_i) G~_ip = -W_i (B 4.25-4.27).
    Linear,
}

/// A linear correction whose moment (its determinant, against W_i^D) is smaller than this
/// fraction of W_i is singular.
pub const SINGULAR_FRACTION: f64 = 1e-10;

/// Per node the correction G~_ip = A_i (G_ip - S_ip r_i): r_i = W'_i / W_i and A_i (the identity
/// for "constant"; -W_i M_i^-T for "linear", M_i = sum_p (x_p - X_i) (x) (G_ip - S_ip r_i)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeCorrection<const D: usize> {
    pub r: [f64; D],
    pub a: [[f64; D]; D],
}

impl<const D: usize> Default for NodeCorrection<D> {
    fn default() -> Self {
        NodeCorrection { r: [0.0; D], a: std::array::from_fn(|b| std::array::from_fn(|c| if b == c { 1.0 } else { 0.0 })) }
    }
}

impl<const D: usize> NodeCorrection<D> {
    /// G~_ip of the gradient `g` and weight `s` of point p at this node.
    #[inline]
    pub fn apply(&self, g: &[f64; D], s: f64) -> [f64; D] {
        let h: [f64; D] = std::array::from_fn(|c| g[c] - s * self.r[c]);
        std::array::from_fn(|b| {
            let mut v = 0.0;
            for c in 0..D {
                v += self.a[b][c] * h[c];
            }
            v
        })
    }
}

/// Per node the correction of the current stencil (see [`NodeCorrection`]). Nodes without points
/// get the identity. Errors name the node whose linear correction is singular. In 1D,
/// A_i = -W_i / M_i is the k_i of the module notes; in 2D/3D it is the RKPM-style extension the
/// notes mark as proposed (A.4): sum_p G~_ip = 0 and sum_p (x_p - X_i) (x) G~_ip = -W_i I, so a
/// constant stress gives no force and a linear stress with equal point volumes the exact one.
pub fn correction_factors<const D: usize>(
    grid: &Grid<D>,
    stencil: &Stencil<D>,
    x: &[[f64; D]],
    kind: GradientCorrection,
    out: &mut Vec<NodeCorrection<D>>,
) -> Result<(), String> {
    let n = grid.node_count();
    out.clear();
    out.resize(n, NodeCorrection::default());
    if kind == GradientCorrection::None {
        return Ok(());
    }
    // Serial sums in point order: the same result for any thread count.
    let mut w = vec![0.0; n];
    let mut dw = vec![[0.0; D]; n];
    for p in 0..x.len() {
        let (nodes, weights, grads) = stencil.row(p);
        for ((&i, &s), g) in nodes.iter().zip(weights).zip(grads) {
            w[i] += s;
            for a in 0..D {
                dw[i][a] += g[a];
            }
        }
    }
    for i in 0..n {
        if w[i] > 0.0 {
            out[i].r = std::array::from_fn(|a| dw[i][a] / w[i]);
        }
    }
    if kind == GradientCorrection::Constant {
        return Ok(());
    }
    let mut moment = vec![[[0.0; D]; D]; n];
    for p in 0..x.len() {
        let (nodes, weights, grads) = stencil.row(p);
        for ((&i, &s), g) in nodes.iter().zip(weights).zip(grads) {
            let xi = grid.node_position(grid.unlinear(i));
            for a in 0..D {
                let mut d = x[p][a] - xi[a];
                if grid.periodic(a) {
                    let len = grid.h[a] * grid.cells[a] as f64;
                    d -= len * (d / len).round();
                }
                for b in 0..D {
                    moment[i][a][b] += d * (g[b] - s * out[i].r[b]);
                }
            }
        }
    }
    for i in 0..n {
        if w[i] <= 0.0 {
            continue;
        }
        let m = &moment[i];
        // det M against W_i^D (M scales as W_i).
        let mut full = tensor::IDENTITY;
        for a in 0..D {
            for b in 0..D {
                full[a][b] = m[a][b];
            }
        }
        let det = tensor::det(&full);
        let singular = !(det.abs() > SINGULAR_FRACTION * w[i].powi(D as i32));
        let inv = if singular { None } else { tensor::inverse(&full) };
        let Some(inv) = inv else {
            return Err(format!(
                "node {:?} (x = {:?} m): the linear-correct derivative's moment sum_p (x_p - X_i) DS**_ip (determinant {:e}) is singular (W_i = {:e}): its points do not span {D} dimension(s) around it",
                grid.unlinear(i),
                grid.node_position(grid.unlinear(i)).map(|v| (v * 1e6).round() / 1e6),
                det,
                w[i]
            ));
        };
        out[i].a = if D == 1 {
            // -W_i / M_i, as before the multi-D form (the same bits).
            std::array::from_fn(|_| std::array::from_fn(|_| -w[i] / m[0][0]))
        } else {
            // A_i = -W_i M_i^-T.
            std::array::from_fn(|b| std::array::from_fn(|c| -w[i] * inv[c][b]))
        };
    }
    Ok(())
}

impl<const D: usize> Simulation<D> {
    /// Fills the correction factors of the current stencil (no-op without a correction).
    pub(super) fn correct_gradients(&mut self, step: u64) -> Result<(), SolverError> {
        if self.gradient_correction == GradientCorrection::None {
            return Ok(());
        }
        correction_factors(&self.grid, &self.stencil, &self.points.x, self.gradient_correction, &mut self.node_correction).map_err(|what| {
            SolverError::Diverged {
                step,
                what,
                cause: "too few points near the node: use gradient_correction = \"constant\" or more points per cell",
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Face;

    /// Hat-function rows of 1D points on `cells` cells of width h from 0.
    fn hat_stencil(h: f64, cells: usize, x: &[f64]) -> (Grid<1>, Stencil<1>, Vec<[f64; 1]>) {
        let grid = Grid { origin: [0.0], h: [h], cells: [cells], faces: [(Face::Free, Face::Free)] };
        let mut part = StencilPart::default();
        part.clear(0);
        for &xp in x {
            let c = ((xp / h).floor() as usize).min(cells - 1);
            let t = xp / h - c as f64;
            part.push(c, 1.0 - t, [-1.0 / h]);
            part.push(c + 1, t, [1.0 / h]);
            part.end_point();
        }
        assert!(x.len() <= CHUNK);
        (grid, Stencil { parts: vec![part] }, x.iter().map(|&v| [v]).collect())
    }

    /// The nodal derivative -sum_p G_ip y_p / W_i (the force's operator) at every node with points.
    fn derivative(grid: &Grid<1>, st: &Stencil<1>, x: &[[f64; 1]], kind: GradientCorrection, y: impl Fn(f64) -> f64) -> Vec<Option<f64>> {
        let mut f = Vec::new();
        correction_factors(grid, st, x, kind, &mut f).unwrap();
        let n = grid.node_count();
        let (mut w, mut d) = (vec![0.0; n], vec![0.0; n]);
        for p in 0..x.len() {
            let (nodes, weights, grads) = st.row(p);
            for ((&i, &s), g) in nodes.iter().zip(weights).zip(grads) {
                let gc = if kind == GradientCorrection::None { g[0] } else { f[i].apply(g, s)[0] };
                w[i] += s;
                d[i] -= gc * y(x[p][0]);
            }
        }
        (0..n).map(|i| if w[i] > 0.0 { Some(d[i] / w[i]) } else { None }).collect()
    }

    /// An irregular set: 3 points per cell at jittered positions (fixed, not random).
    fn irregular() -> Vec<f64> {
        let h = 0.1;
        let mut x = Vec::new();
        for c in 0..8 {
            for (k, j) in [0.13, 0.47, 0.81].iter().enumerate() {
                let jitter = 0.09 * (((c * 7 + k * 3) % 5) as f64 - 2.0) / 2.0;
                x.push(h * (c as f64 + j + jitter));
            }
        }
        x
    }

    #[test]
    fn constant_correct_annihilates_constants_where_the_plain_gradient_does_not() {
        let (g, st, x) = hat_stencil(0.1, 8, &irregular());
        let plain = derivative(&g, &st, &x, GradientCorrection::None, |_| 2.5);
        let worst_plain = plain.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
        assert!(worst_plain > 1.0, "the plain gradient should not annihilate constants here: {worst_plain}");
        for kind in [GradientCorrection::Constant, GradientCorrection::Linear] {
            for (i, d) in derivative(&g, &st, &x, kind, |_| 2.5).iter().enumerate() {
                let d = d.unwrap();
                assert!(d.abs() < 1e-11, "{kind:?} node {i}: {d}");
            }
        }
    }

    #[test]
    fn linear_correct_reproduces_a_linear_slope_where_the_others_do_not() {
        let (g, st, x) = hat_stencil(0.1, 8, &irregular());
        let y = |v: f64| 3.0 - 7.0 * v;
        let err = |kind| derivative(&g, &st, &x, kind, y).iter().flatten().fold(0.0f64, |a, v| a.max((v + 7.0).abs()));
        assert!(err(GradientCorrection::None) > 0.5, "plain: {}", err(GradientCorrection::None));
        assert!(err(GradientCorrection::Constant) > 0.5, "constant: {}", err(GradientCorrection::Constant));
        assert!(err(GradientCorrection::Linear) < 1e-11, "linear: {}", err(GradientCorrection::Linear));
        // A quadratic: exact only on symmetric points (uniform quarter-cell points, interior nodes).
        let q = |v: f64| v * v;
        let irregular_q = derivative(&g, &st, &x, GradientCorrection::Linear, q);
        let worst = (1..8).map(|i| (irregular_q[i].unwrap() - 2.0 * 0.1 * i as f64).abs()).fold(0.0, f64::max);
        assert!(worst > 1e-4, "a quadratic is not reproduced on irregular points: {worst}");
        let uniform: Vec<f64> = (0..16).map(|k| 0.1 * (k as f64 + 0.5) / 2.0).collect();
        let (g, st, x) = hat_stencil(0.1, 8, &uniform);
        let d = derivative(&g, &st, &x, GradientCorrection::Linear, q);
        for i in 1..8 {
            assert!((d[i].unwrap() - 2.0 * 0.1 * i as f64).abs() < 1e-12, "node {i}: {:?}", d[i]);
        }
    }

    /// Bilinear rows of 2D points on cells x cells cells of width h from the origin.
    fn hat_stencil_2d(h: f64, cells: usize, x: &[[f64; 2]]) -> (Grid<2>, Stencil<2>) {
        let grid = Grid { origin: [0.0; 2], h: [h; 2], cells: [cells; 2], faces: std::array::from_fn(|_| (Face::Free, Face::Free)) };
        let mut part = StencilPart::default();
        part.clear(0);
        for xp in x {
            let c: [usize; 2] = std::array::from_fn(|a| ((xp[a] / h).floor() as usize).min(cells - 1));
            let t: [f64; 2] = std::array::from_fn(|a| xp[a] / h - c[a] as f64);
            for (di, dj) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (wx, gx) = if di == 1 { (t[0], 1.0 / h) } else { (1.0 - t[0], -1.0 / h) };
                let (wy, gy) = if dj == 1 { (t[1], 1.0 / h) } else { (1.0 - t[1], -1.0 / h) };
                part.push(grid.linear([c[0] + di, c[1] + dj]), wx * wy, [gx * wy, wx * gy]);
            }
            part.end_point();
        }
        assert!(x.len() <= CHUNK);
        (grid, Stencil { parts: vec![part] })
    }

    #[test]
    fn the_2d_linear_correction_reproduces_a_linear_gradient_on_irregular_points() {
        let (h, cells) = (0.1, 5);
        // 3 x 3 jittered points per cell (fixed, not random).
        let mut x = Vec::new();
        for cj in 0..cells {
            for ci in 0..cells {
                for (k, (a, b)) in
                    [(0.15, 0.2), (0.5, 0.1), (0.85, 0.25), (0.1, 0.5), (0.55, 0.45), (0.9, 0.6), (0.2, 0.85), (0.45, 0.9), (0.8, 0.8)]
                        .iter()
                        .enumerate()
                {
                    let j = 0.05 * (((ci * 5 + cj * 3 + k) % 5) as f64 - 2.0) / 2.0;
                    x.push([h * (ci as f64 + a + j), h * (cj as f64 + b - j)]);
                }
            }
        }
        let (grid, st) = hat_stencil_2d(h, cells, &x);
        let y = |p: &[f64; 2]| 1.5 + 4.0 * p[0] - 7.0 * p[1];
        // The nodal gradient -sum_p G~_ip y_p / W_i at every node, against (4, -7).
        let worst = |kind| {
            let mut f = Vec::new();
            correction_factors(&grid, &st, &x, kind, &mut f).unwrap();
            let n = grid.node_count();
            let (mut w, mut d) = (vec![0.0; n], vec![[0.0; 2]; n]);
            for p in 0..x.len() {
                let (nodes, weights, grads) = st.row(p);
                for ((&i, &s), g) in nodes.iter().zip(weights).zip(grads) {
                    let gc = if kind == GradientCorrection::None { *g } else { f[i].apply(g, s) };
                    w[i] += s;
                    for a in 0..2 {
                        d[i][a] -= gc[a] * y(&x[p]);
                    }
                }
            }
            (0..n).filter(|&i| w[i] > 0.0).map(|i| (d[i][0] / w[i] - 4.0).abs().max((d[i][1] / w[i] + 7.0).abs())).fold(0.0, f64::max)
        };
        assert!(worst(GradientCorrection::None) > 1.0, "plain: {}", worst(GradientCorrection::None));
        assert!(worst(GradientCorrection::Constant) > 1.0, "constant: {}", worst(GradientCorrection::Constant));
        assert!(worst(GradientCorrection::Linear) < 1e-10, "linear: {}", worst(GradientCorrection::Linear));
        // A corner node touched by points on a line only is singular, and named.
        let line: Vec<[f64; 2]> = (0..4).map(|k| [0.02 + 0.02 * k as f64, 0.05]).collect();
        let (grid, st) = hat_stencil_2d(h, 1, &line);
        let e = correction_factors(&grid, &st, &line, GradientCorrection::Linear, &mut Vec::new()).unwrap_err();
        assert!(e.contains("singular") && e.contains("do not span 2 dimension(s)"), "{e}");
    }

    #[test]
    fn a_node_with_one_point_is_singular_and_named() {
        // The last point alone touches node 3.
        let (g, st, x) = hat_stencil(0.1, 3, &[0.02, 0.07, 0.12, 0.17, 0.25]);
        let mut f = Vec::new();
        let e = correction_factors(&g, &st, &x, GradientCorrection::Linear, &mut f).unwrap_err();
        assert!(e.starts_with("node [3] (x = [0.3] m)") && e.contains("singular"), "{e}");
        correction_factors(&g, &st, &x, GradientCorrection::Constant, &mut f).expect("the constant correction has no singular case");
    }
}
