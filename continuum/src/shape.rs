//! Shape functions and their gradients, reduced to a [`Stencil`] per step.
//!
//! A scheme is a name from the scene (`mpm`, `ugimp`, ...) and a way to fill the stencil:
//! for every point, the nodes it interacts with, the weight S_ip used to map mass and momentum,
//! and the gradient G_ip used for internal forces and the velocity gradient. In MPM and GIMP
//! G_ip is the gradient of S_ip; modified-gradient schemes (DDMP) change G only.

use crate::grid::Grid;
use crate::particles::Particles;

/// The gradient schemes a scene can name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SchemeKind {
    /// Linear hat functions evaluated at the point.
    Mpm,
    /// GIMP with the point's domain kept at its initial size.
    Ugimp,
    /// GIMP with the domain stretched by the diagonal of the deformation gradient.
    Cpgimp,
}

impl SchemeKind {
    /// Scene names of the schemes this build implements.
    pub const NAMES: &'static [(&'static str, SchemeKind)] =
        &[("mpm", SchemeKind::Mpm), ("ugimp", SchemeKind::Ugimp), ("cpgimp", SchemeKind::Cpgimp)];

    pub fn from_name(name: &str) -> Option<SchemeKind> {
        Self::NAMES.iter().find(|(n, _)| *n == name).map(|(_, k)| *k)
    }

    pub fn name(self) -> &'static str {
        Self::NAMES.iter().find(|(_, k)| *k == self).map(|(n, _)| *n).unwrap_or("?")
    }
}

/// Per-point node lists in compressed rows: point p owns entries `offsets[p]..offsets[p+1]`.
#[derive(Debug, Clone, Default)]
pub struct Stencil<const D: usize> {
    pub offsets: Vec<usize>,
    pub node: Vec<usize>,
    pub weight: Vec<f64>,
    pub grad: Vec<[f64; D]>,
}

impl<const D: usize> Stencil<D> {
    pub fn clear(&mut self) {
        self.offsets.clear();
        self.offsets.push(0);
        self.node.clear();
        self.weight.clear();
        self.grad.clear();
    }

    pub fn entries(&self, p: usize) -> std::ops::Range<usize> {
        self.offsets[p]..self.offsets[p + 1]
    }
}

/// A point that the stencil cannot place on the grid.
#[derive(Debug, Clone, PartialEq)]
pub struct OutsideGrid {
    pub point: usize,
    pub axis: usize,
    pub position: f64,
}

/// 1D linear hat function of `r = x_p - x_i` and its derivative.
fn hat(r: f64, h: f64) -> (f64, f64) {
    let a = r.abs();
    if a >= h { (0.0, 0.0) } else { (1.0 - a / h, -r.signum() / h) }
}

/// 1D GIMP effective shape function of `r = x_p - x_i` for a point domain of half-length `lp`
/// (<= h/2), and its derivative with respect to x_p. Gong (2015) Ch. 6.3 with the sign of the
/// last gradient branch corrected (see shared/seeds/README.md).
pub fn gimp(r: f64, h: f64, lp: f64) -> (f64, f64) {
    let a = r.abs();
    let s = r.signum();
    if a < lp {
        (1.0 - (r * r + lp * lp) / (2.0 * h * lp), -r / (h * lp))
    } else if a < h - lp {
        (1.0 - a / h, -s / h)
    } else if a < h + lp {
        let d = h + lp - a;
        (d * d / (4.0 * h * lp), -s * d / (2.0 * h * lp))
    } else {
        (0.0, 0.0)
    }
}

/// Fills `out` with the stencil of every point for `kind`.
pub fn build<const D: usize>(
    kind: SchemeKind,
    grid: &Grid<D>,
    pts: &Particles<D>,
    out: &mut Stencil<D>,
) -> Result<(), OutsideGrid> {
    out.clear();
    // Per-axis 1D factors: (node index along the axis, S, dS).
    let mut axis_terms: [Vec<(usize, f64, f64)>; D] = std::array::from_fn(|_| Vec::with_capacity(4));
    for p in 0..pts.len() {
        for a in 0..D {
            let h = grid.h[a];
            let lp = match kind {
                SchemeKind::Mpm => 0.0,
                SchemeKind::Ugimp => pts.half_length[p][a],
                SchemeKind::Cpgimp => (pts.half_length[p][a] * pts.def_grad[p][a][a]).min(0.5 * h),
            };
            let xi = (pts.x[p][a] - grid.origin[a]) / h;
            let reach = if lp > 0.0 { 1.0 + lp / h } else { 1.0 };
            let lo = (xi - reach).floor() as i64;
            let hi = (xi + reach).ceil() as i64;
            let terms = &mut axis_terms[a];
            terms.clear();
            for i in lo..=hi {
                let r = pts.x[p][a] - (grid.origin[a] + h * i as f64);
                let (s, ds) = if lp > 0.0 { gimp(r, h, lp) } else { hat(r, h) };
                // Round-off at the edge of the support (a domain touching the grid's boundary)
                // must not reach a node outside the grid.
                if s.abs() < 1e-12 && (ds * h).abs() < 1e-9 {
                    continue;
                }
                let node = grid.wrap(a, i).ok_or(OutsideGrid { point: p, axis: a, position: pts.x[p][a] })?;
                terms.push((node, s, ds));
            }
        }
        push_tensor_product(grid, &axis_terms, out);
        out.offsets.push(out.node.len());
    }
    Ok(())
}

/// Appends the tensor product of per-axis factors as stencil entries of one point.
fn push_tensor_product<const D: usize>(grid: &Grid<D>, axis_terms: &[Vec<(usize, f64, f64)>; D], out: &mut Stencil<D>) {
    let counts: [usize; D] = std::array::from_fn(|a| axis_terms[a].len());
    let total: usize = counts.iter().product();
    for k in 0..total {
        let mut rem = k;
        let pick: [usize; D] = std::array::from_fn(|a| {
            let c = rem % counts[a];
            rem /= counts[a];
            c
        });
        let idx: [usize; D] = std::array::from_fn(|a| axis_terms[a][pick[a]].0);
        let mut w = 1.0;
        for a in 0..D {
            w *= axis_terms[a][pick[a]].1;
        }
        let g: [f64; D] = std::array::from_fn(|b| {
            let mut gb = 1.0;
            for a in 0..D {
                let t = axis_terms[a][pick[a]];
                gb *= if a == b { t.2 } else { t.1 };
            }
            gb
        });
        out.node.push(grid.linear(idx));
        out.weight.push(w);
        out.grad.push(g);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gimp_is_partition_of_unity_with_zero_gradient_sum() {
        let h = 0.1;
        for lp in [0.0125, 0.025, 0.05] {
            for k in 0..200 {
                let x = 0.3 + 0.1 * k as f64 / 200.0;
                let (mut s, mut g) = (0.0, 0.0);
                for i in 0..10 {
                    let (si, gi) = gimp(x - h * i as f64, h, lp);
                    s += si;
                    g += gi;
                }
                assert!((s - 1.0).abs() < 1e-13, "sum S = {s} at x = {x}");
                assert!(g.abs() < 1e-10, "sum grad S = {g} at x = {x}");
            }
        }
    }

    #[test]
    fn gimp_gradient_matches_finite_difference() {
        let (h, lp) = (1.0, 0.2);
        for k in 0..400 {
            let r = -1.3 + 2.6 * k as f64 / 400.0 + 1e-3;
            let e = 1e-7;
            let fd = (gimp(r + e, h, lp).0 - gimp(r - e, h, lp).0) / (2.0 * e);
            assert!((fd - gimp(r, h, lp).1).abs() < 1e-5, "r = {r}: fd {fd} vs {}", gimp(r, h, lp).1);
        }
    }
}
