//! Moving-least-squares (reproducing-kernel) reconstruction of point data at arbitrary targets
//! (Gong, Ch. 3 and 5.1; notes A.1).
//!
//! Data u_p sit at points x_p; the reconstruction at x is u^h(x) = sum_p Phi_p(x) u_p with
//!
//! ```text
//! Phi_p(x) = w(x - x_p) b(x - x_p)^T M(x)^{-1} b(0),   M(x) = sum_p w(x - x_p) b(x - x_p) b(x - x_p)^T
//! ```
//!
//! (G 3.7-3.8, with the erratum of (3.8): the last factor is b(0), not b(x - x_p); this shifted
//! form is Gong's Algorithm 1). The basis is `Shepard` (b = \[1\], Gong's "first-order MLS":
//! Phi_p = w_p / sum w, a partition of unity) or `Linear` (b = [1, y_1, .., y_D], "second-order
//! MLS", which reproduces every linear field exactly, G 3.21). The basis is scaled by the
//! spacing, b = [1, y/h], so M is O(1) whatever the units; the shape functions do not change.
//!
//! Weights are tensor products of one-dimensional kernels in xi = |x - x_p| / h per axis:
//! - `Hat`: 1 - xi on xi < 1 (the linear hat of G 4.8, used for Table 4.1);
//! - `QuadraticBSpline` (G 5.2, for density and stress at cell centres): 3/4 - xi^2 for
//!   xi <= 1/2, (3/2 - xi)^2 / 2 for xi <= 3/2 (support radius 1.5 h: erratum of the printed
//!   "3/(2h)");
//! - `CubicBSpline` (G 5.1, for velocity at nodes): 2/3 - xi^2 + xi^3 / 2 for xi < 1,
//!   (2 - xi)^3 / 6 for xi < 2 (Gong's r = |x - x_p|/(2h) form rewritten; the node weight
//!   printed "3/2 + .." is 2/3 + ..).
//!
//! A target whose support holds no point gets an empty row when the caller asks for
//! [`Empty::Skip`] (nodes or cell centres outside the body); a support with points whose moment
//! matrix is singular (fewer than D + 1 points for the linear basis, or all on one line or
//! plane) is an error, [`SingularMoment`], naming the target (node or cell centre) and how many
//! points it saw.

use nalgebra::{SMatrix, SVector};

/// The polynomial basis of the reconstruction.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Basis {
    /// b = \[1\]: Shepard functions, Phi_p = w_p / sum_q w_q (reproduces constants).
    Shepard,
    /// b = [1, y]: reproduces linear fields.
    Linear,
}

/// The weight (kernel) of the reconstruction: a tensor product of 1D kernels in |x - x_p| / h.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Weight {
    /// Linear hat, support radius h.
    Hat,
    /// Quadratic B-spline, support radius 1.5 h (G 5.2).
    QuadraticBSpline,
    /// Cubic B-spline, support radius 2 h (G 5.1).
    CubicBSpline,
}

impl Weight {
    /// Support radius in units of h.
    pub fn radius(self) -> f64 {
        match self {
            Weight::Hat => 1.0,
            Weight::QuadraticBSpline => 1.5,
            Weight::CubicBSpline => 2.0,
        }
    }

    /// The 1D kernel at xi = |x - x_p| / h.
    pub fn kernel(self, xi: f64) -> f64 {
        let r = xi.abs();
        match self {
            Weight::Hat => (1.0 - r).max(0.0),
            Weight::QuadraticBSpline => {
                if r <= 0.5 {
                    0.75 - r * r
                } else if r < 1.5 {
                    0.5 * (1.5 - r) * (1.5 - r)
                } else {
                    0.0
                }
            }
            Weight::CubicBSpline => {
                if r < 1.0 {
                    2.0 / 3.0 - r * r + 0.5 * r * r * r
                } else if r < 2.0 {
                    (2.0 - r).powi(3) / 6.0
                } else {
                    0.0
                }
            }
        }
    }
}

/// What a target with no point in its support gets.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Empty {
    /// An empty row (the reconstruction there is undefined; the caller leaves it out).
    Skip,
    /// A [`SingularMoment`] error, as for any other singular support.
    Refuse,
}

/// A target whose moment matrix M is singular (or too ill-conditioned to invert).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error(
    "MLS reconstruction ({basis:?} basis, {weight:?} weight): the moment matrix at {kind} {index} (x = {position:?} m) is singular: \
     {points} point(s) in its support of radius {radius} h, reciprocal condition {rcond:.1e}; a {basis:?} basis needs at least {needed} \
     points not on one line or plane there. Use more particles per cell, a wider weight, or the Shepard basis"
)]
pub struct SingularMoment {
    /// What the targets are: "node", "cell centre", "point".
    pub kind: &'static str,
    /// Index of the target in the caller's list (a node's linear index, a cell's index).
    pub index: usize,
    pub position: Vec<f64>,
    pub points: usize,
    pub radius: f64,
    pub needed: usize,
    pub rcond: f64,
    pub basis: Basis,
    pub weight: Weight,
}

/// Smallest reciprocal condition number (smallest over largest singular value of the scaled M)
/// accepted.
pub const MIN_RCOND: f64 = 1e-10;

/// The reconstruction's settings: basis, weight and spacing h per axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mls<const D: usize> {
    pub basis: Basis,
    pub weight: Weight,
    /// Kernel spacing per axis (m): the cell size.
    pub h: [f64; D],
}

/// Shape functions of many targets in compressed rows: target `t` has entries
/// `offsets[t]..offsets[t + 1]` of `point` (indices into the point list) and `phi`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ShapeTable {
    pub offsets: Vec<usize>,
    pub point: Vec<usize>,
    pub phi: Vec<f64>,
}

impl ShapeTable {
    /// Points and shape-function values of target `t`.
    pub fn row(&self, t: usize) -> (&[usize], &[f64]) {
        let r = self.offsets[t]..self.offsets[t + 1];
        (&self.point[r.clone()], &self.phi[r])
    }

    /// Number of targets.
    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether target `t` has a reconstruction (a non-empty support).
    pub fn has(&self, t: usize) -> bool {
        self.offsets[t + 1] > self.offsets[t]
    }

    /// sum_p Phi_p(x_t) u_p for a scalar field `u` over the points.
    pub fn apply(&self, t: usize, u: &[f64]) -> f64 {
        let (p, phi) = self.row(t);
        p.iter().zip(phi).map(|(&p, &f)| f * u[p]).sum()
    }
}

/// Points sorted into cells of size h, to find a target's support without scanning every point.
#[derive(Debug, Clone)]
struct Bins<const D: usize> {
    origin: [f64; D],
    h: [f64; D],
    dims: [usize; D],
    offsets: Vec<usize>,
    items: Vec<usize>,
}

impl<const D: usize> Bins<D> {
    fn new(points: &[[f64; D]], h: [f64; D]) -> Self {
        let mut lo = [f64::INFINITY; D];
        let mut hi = [f64::NEG_INFINITY; D];
        for x in points {
            for a in 0..D {
                lo[a] = lo[a].min(x[a]);
                hi[a] = hi[a].max(x[a]);
            }
        }
        if points.is_empty() {
            lo = [0.0; D];
            hi = [0.0; D];
        }
        let dims: [usize; D] = std::array::from_fn(|a| ((hi[a] - lo[a]) / h[a]).floor() as usize + 1);
        let total: usize = dims.iter().product();
        let cell_of = |x: &[f64; D]| -> usize {
            let mut lin = 0;
            for a in (0..D).rev() {
                let c = (((x[a] - lo[a]) / h[a]).floor() as usize).min(dims[a] - 1);
                lin = lin * dims[a] + c;
            }
            lin
        };
        let mut counts = vec![0usize; total + 1];
        for x in points {
            counts[cell_of(x) + 1] += 1;
        }
        for k in 0..total {
            counts[k + 1] += counts[k];
        }
        let mut fill = counts.clone();
        let mut items = vec![0; points.len()];
        for (p, x) in points.iter().enumerate() {
            let c = cell_of(x);
            items[fill[c]] = p;
            fill[c] += 1;
        }
        Bins { origin: lo, h, dims, offsets: counts, items }
    }

    /// Calls `f` with every point in the bins within `radius` cells of `x` (a superset of the
    /// support), in increasing bin order.
    fn for_each_near(&self, x: &[f64; D], radius: f64, mut f: impl FnMut(usize)) {
        let mut lo = [0usize; D];
        let mut hi = [0usize; D];
        for a in 0..D {
            let l = ((x[a] - radius * self.h[a] - self.origin[a]) / self.h[a]).floor();
            let u = ((x[a] + radius * self.h[a] - self.origin[a]) / self.h[a]).floor();
            if !(u >= 0.0 && l <= (self.dims[a] - 1) as f64) {
                return;
            }
            lo[a] = l.max(0.0) as usize;
            hi[a] = (u as usize).min(self.dims[a] - 1);
        }
        let mut idx = lo;
        loop {
            let mut lin = 0;
            for a in (0..D).rev() {
                lin = lin * self.dims[a] + idx[a];
            }
            for &p in &self.items[self.offsets[lin]..self.offsets[lin + 1]] {
                f(p);
            }
            let mut a = 0;
            loop {
                if idx[a] < hi[a] {
                    idx[a] += 1;
                    break;
                }
                idx[a] = lo[a];
                a += 1;
                if a == D {
                    return;
                }
            }
        }
    }
}

/// Size of the largest basis (1 + D, D <= 3).
const NB: usize = 4;

impl<const D: usize> Mls<D> {
    pub fn new(basis: Basis, weight: Weight, h: [f64; D]) -> Self {
        Mls { basis, weight, h }
    }

    /// Number of basis functions.
    pub fn basis_len(&self) -> usize {
        match self.basis {
            Basis::Shepard => 1,
            Basis::Linear => 1 + D,
        }
    }

    /// The weight w(x - x_p) (tensor product).
    pub fn weight_at(&self, x: &[f64; D], xp: &[f64; D]) -> f64 {
        let mut w = 1.0;
        for a in 0..D {
            w *= self.weight.kernel((x[a] - xp[a]) / self.h[a]);
            if w == 0.0 {
                break;
            }
        }
        w
    }

    fn scaled_basis(&self, x: &[f64; D], xp: &[f64; D]) -> SVector<f64, NB> {
        let mut b = SVector::<f64, NB>::zeros();
        b[0] = 1.0;
        if self.basis == Basis::Linear {
            for a in 0..D {
                b[1 + a] = (x[a] - xp[a]) / self.h[a];
            }
        }
        b
    }

    /// Phi_p(x) for the candidate points (those with w > 0 are pushed to `out` as (p, Phi_p),
    /// in candidate order). Returns the number of points in the support, or `Err((count, rcond))`
    /// when M is singular.
    pub fn shape_functions(
        &self,
        x: &[f64; D],
        points: &[[f64; D]],
        candidates: impl IntoIterator<Item = usize>,
        out: &mut Vec<(usize, f64)>,
    ) -> Result<usize, (usize, f64)> {
        let start = out.len();
        let n = self.basis_len();
        let mut m = SMatrix::<f64, NB, NB>::zeros();
        for p in candidates {
            let w = self.weight_at(x, &points[p]);
            if w > 0.0 {
                let b = self.scaled_basis(x, &points[p]);
                m += (b * b.transpose()) * w;
                out.push((p, w));
            }
        }
        let count = out.len() - start;
        if count == 0 {
            return Err((0, 0.0));
        }
        // The unused rows and columns of the padded 4 x 4 matrix decouple: put 1 on their diagonal.
        for k in n..NB {
            m[(k, k)] = 1.0;
        }
        let rcond = if n == 1 {
            1.0
        } else {
            let sv = m.fixed_view::<NB, NB>(0, 0).into_owned().singular_values();
            let (mut smin, mut smax) = (f64::INFINITY, 0.0_f64);
            for k in 0..NB {
                smin = smin.min(sv[k]);
                smax = smax.max(sv[k]);
            }
            if smax > 0.0 { smin / smax } else { 0.0 }
        };
        let e1 = SVector::<f64, NB>::from_fn(|k, _| if k == 0 { 1.0 } else { 0.0 });
        let a = if n == 1 {
            Some(e1 / m[(0, 0)])
        } else if rcond >= MIN_RCOND {
            m.lu().solve(&e1)
        } else {
            None
        };
        let Some(a) = a.filter(|a| a.iter().all(|v| v.is_finite())) else {
            out.truncate(start);
            return Err((count, rcond));
        };
        for entry in &mut out[start..] {
            let b = self.scaled_basis(x, &points[entry.0]);
            entry.1 *= b.dot(&a);
        }
        Ok(count)
    }

    /// The shape functions of every target over `points`: row `t` of the table holds the points
    /// in the support of `targets[t]` (in increasing point order) and their Phi_p. `kind` names
    /// the targets in errors ("node", "cell centre"); `index_of(t)` gives the index reported.
    pub fn table(
        &self,
        targets: &[[f64; D]],
        points: &[[f64; D]],
        empty: Empty,
        kind: &'static str,
        index_of: impl Fn(usize) -> usize,
    ) -> Result<ShapeTable, SingularMoment> {
        let bins = Bins::new(points, self.h);
        let radius = self.weight.radius();
        let mut table = ShapeTable { offsets: vec![0], point: Vec::new(), phi: Vec::new() };
        let mut near = Vec::new();
        let mut row = Vec::new();
        for (t, x) in targets.iter().enumerate() {
            near.clear();
            bins.for_each_near(x, radius, |p| near.push(p));
            near.sort_unstable();
            row.clear();
            match self.shape_functions(x, points, near.iter().copied(), &mut row) {
                Ok(_) => {}
                Err((0, _)) if empty == Empty::Skip => {}
                Err((count, rcond)) => {
                    return Err(SingularMoment {
                        kind,
                        index: index_of(t),
                        position: x.to_vec(),
                        points: count,
                        radius,
                        needed: self.basis_len(),
                        rcond,
                        basis: self.basis,
                        weight: self.weight,
                    });
                }
            }
            for &(p, f) in &row {
                table.point.push(p);
                table.phi.push(f);
            }
            table.offsets.push(table.point.len());
        }
        Ok(table)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (xorshift64*), so the tests need no crate.
    struct Rng(u64);
    impl Rng {
        fn uniform(&mut self) -> f64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    fn nodes_1d(n: usize, lo: f64, h: f64) -> Vec<[f64; 1]> {
        (0..n).map(|i| [lo + i as f64 * h]).collect()
    }

    /// Gong Table 4.1: Shepard with hat weights, 11 nodes on [-1, 1] (h = 0.2: the text's
    /// h = 1/10 is an erratum), 4 cell-centred points per element, M_p = 1. Exact values:
    /// 1 - u^h = 0; x_i - u^h = -0.06875 (node 1), +0.06875 (node 11), 0 inside;
    /// x_i^2 - u^h = 0.130625 at both ends, -0.006875 = -(11/64) h^2 inside.
    #[test]
    fn gong_table_4_1_is_reproduced() {
        let h = 0.2;
        let nodes = nodes_1d(11, -1.0, h);
        let points: Vec<[f64; 1]> = (0..40).map(|k| [-1.0 + (k as f64 + 0.5) * h / 4.0]).collect();
        let mls = Mls::new(Basis::Shepard, Weight::Hat, [h]);
        let t = mls.table(&nodes, &points, Empty::Refuse, "node", |i| i).expect("every node has points");
        let field = |f: &dyn Fn(f64) -> f64| points.iter().map(|x| f(x[0])).collect::<Vec<f64>>();
        let (one, lin, quad) = (field(&|_| 1.0), field(&|x| x), field(&|x| x * x));
        for (i, x) in nodes.iter().enumerate() {
            let x = x[0];
            assert!((1.0 - t.apply(i, &one)).abs() < 1e-12, "node {}", i + 1);
            let e_lin = x - t.apply(i, &lin);
            let want_lin = match i {
                0 => -0.06875,
                10 => 0.06875,
                _ => 0.0,
            };
            assert!((e_lin - want_lin).abs() < 1e-12, "u = x, node {}: {e_lin} vs {want_lin}", i + 1);
            let e_quad = x * x - t.apply(i, &quad);
            let want_quad = if i == 0 || i == 10 { 0.130625 } else { -0.006875 };
            assert!((e_quad - want_quad).abs() < 1e-12, "u = x^2, node {}: {e_quad} vs {want_quad}", i + 1);
        }
        assert!((-(11.0 / 64.0) * h * h - -0.006875_f64).abs() < 1e-15);
    }

    /// The linear basis reproduces linear fields exactly on random points, with either
    /// B-spline weight, in 1D, 2D and 3D (G 3.21), at targets anywhere the support is full.
    fn linear_reproduction<const D: usize>(weight: Weight, seed: u64) {
        let mut rng = Rng(seed);
        let cells = if D == 3 { 4 } else { 8 };
        let h = 1.0 / cells as f64;
        let per_axis = if D == 3 { 2usize } else { 4 };
        let n = (cells * per_axis).pow(D as u32);
        let points: Vec<[f64; D]> = (0..n).map(|_| std::array::from_fn(|_| rng.uniform())).collect();
        let coef: [f64; D] = std::array::from_fn(|a| 0.7 - 1.3 * a as f64);
        let u: Vec<f64> = points.iter().map(|x| 0.25 + (0..D).map(|a| coef[a] * x[a]).sum::<f64>()).collect();
        let targets: Vec<[f64; D]> = (0..50).map(|_| std::array::from_fn(|_| h + (1.0 - 2.0 * h) * rng.uniform())).collect();
        let mls = Mls::new(Basis::Linear, weight, [h; D]);
        let t = mls.table(&targets, &points, Empty::Refuse, "point", |i| i).expect("random supports are full");
        let mut worst: f64 = 0.0;
        for (k, x) in targets.iter().enumerate() {
            let exact = 0.25 + (0..D).map(|a| coef[a] * x[a]).sum::<f64>();
            worst = worst.max((t.apply(k, &u) - exact).abs());
            let (_, phi) = t.row(k);
            assert!((phi.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        assert!(worst < 1e-12, "{D}D {weight:?}: largest error {worst:e}");
    }

    #[test]
    fn the_linear_basis_reproduces_linear_fields_on_random_points() {
        for seed in [1, 7, 12345] {
            linear_reproduction::<1>(Weight::CubicBSpline, seed);
            linear_reproduction::<1>(Weight::QuadraticBSpline, seed);
            linear_reproduction::<2>(Weight::CubicBSpline, seed);
            linear_reproduction::<2>(Weight::QuadraticBSpline, seed);
            linear_reproduction::<3>(Weight::CubicBSpline, seed);
        }
    }

    #[test]
    fn the_b_spline_kernels_are_partitions_of_unity_and_match_gongs_forms() {
        for k in 0..=200 {
            let s = k as f64 / 200.0;
            let cubic: f64 = (-3..=3).map(|i| Weight::CubicBSpline.kernel(s - i as f64)).sum();
            let quad: f64 = (-3..=3).map(|i| Weight::QuadraticBSpline.kernel(s - i as f64)).sum();
            assert!((cubic - 1.0).abs() < 1e-14 && (quad - 1.0).abs() < 1e-14, "{s}: {cubic} {quad}");
            // Gong 5.1 in r = |x - x_p| / (2h).
            let xi = 2.0 * s;
            let r = xi / 2.0;
            let gong = if r <= 0.5 {
                2.0 / 3.0 - 4.0 * r * r + 4.0 * r.powi(3)
            } else {
                4.0 / 3.0 - 4.0 * r + 4.0 * r * r - 4.0 / 3.0 * r.powi(3)
            };
            assert!((Weight::CubicBSpline.kernel(xi) - gong).abs() < 1e-14);
        }
        assert_eq!(Weight::QuadraticBSpline.kernel(1.5), 0.0);
        assert_eq!(Weight::CubicBSpline.kernel(2.0), 0.0);
    }

    #[test]
    fn a_singular_moment_matrix_names_its_node() {
        // Two points, both left of node 3 at the same place: the linear basis cannot fit a slope.
        let h = 0.1;
        let nodes = nodes_1d(5, 0.0, h);
        let points = vec![[0.21], [0.21]];
        let mls = Mls::new(Basis::Linear, Weight::QuadraticBSpline, [h]);
        let e = mls.table(&nodes, &points, Empty::Skip, "node", |i| i).unwrap_err();
        assert_eq!((e.kind, e.points), ("node", 2));
        assert!([1, 2, 3].contains(&e.index), "{e}");
        let msg = e.to_string();
        assert!(msg.contains("moment matrix at node") && msg.contains("singular") && msg.contains("2 point(s)"), "{msg}");
        // Shepard is fine with one point, and skipped targets get empty rows.
        let s = Mls::new(Basis::Shepard, Weight::QuadraticBSpline, [h]);
        let t = s.table(&nodes, &points, Empty::Skip, "node", |i| i).expect("shepard");
        assert!(!t.has(0) && t.has(2) && !t.has(4));
        assert!(s.table(&nodes, &points, Empty::Refuse, "node", |i| i).is_err());
    }

    /// Interior max-norm error of u = sin(pi x) at the nodes of [0, 1] from 4 points per cell.
    fn interior_error(basis: Basis, weight: Weight, cells: usize, jitter: f64, seed: u64) -> f64 {
        let h = 1.0 / cells as f64;
        let mut rng = Rng(seed);
        let ppc = 4;
        let points: Vec<[f64; 1]> =
            (0..cells * ppc).map(|k| [(k as f64 + 0.5 + jitter * (rng.uniform() - 0.5)) * h / ppc as f64]).collect();
        let u: Vec<f64> = points.iter().map(|x| (std::f64::consts::PI * x[0]).sin()).collect();
        let nodes = nodes_1d(cells + 1, 0.0, h);
        let t = Mls::new(basis, weight, [h]).table(&nodes, &points, Empty::Refuse, "node", |i| i).expect("full supports");
        (2..cells - 1).map(|i| (t.apply(i, &u) - (std::f64::consts::PI * nodes[i][0]).sin()).abs()).fold(0.0, f64::max)
    }

    /// Notes A.1: Shepard is second order in the interior on uniform points and loses it on
    /// jittered ones; the linear basis keeps second order on jittered points.
    #[test]
    fn interior_convergence_orders() {
        let order = |e: &dyn Fn(usize) -> f64| (e(20) / e(160)).log2() / 3.0;
        let shepard_uniform = order(&|n| interior_error(Basis::Shepard, Weight::Hat, n, 0.0, 1));
        let mls2_jittered = order(&|n| interior_error(Basis::Linear, Weight::CubicBSpline, n, 0.9, 3));
        let shepard_jittered: f64 =
            [5, 6, 7, 8].iter().map(|&s| order(&|n| interior_error(Basis::Shepard, Weight::Hat, n, 0.9, s))).sum::<f64>() / 4.0;
        assert!(shepard_uniform >= 1.9, "{shepard_uniform}");
        assert!(mls2_jittered >= 1.9, "{mls2_jittered}");
        assert!(shepard_jittered <= 1.3, "{shepard_jittered}");
    }
}
