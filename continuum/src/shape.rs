//! Shape functions and their gradients, reduced to a [`Stencil`] per step.
//!
//! A scheme is a name from the scene (`mpm`, `ugimp`, ...) and a way to fill the stencil:
//! for every point, the nodes it interacts with, the weight S_ip used to map mass and momentum,
//! and the gradient G_ip used for internal forces and the velocity gradient. In MPM and GIMP
//! G_ip is the gradient of S_ip; modified-gradient schemes (DDMP) change G only.

use crate::grid::Grid;
use crate::par::CHUNK;
use crate::particles::Particles;
use std::ops::Range;

/// The gradient schemes a scene can name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SchemeKind {
    /// Linear hat functions evaluated at the point.
    Mpm,
    /// GIMP with the point's domain kept at its initial size.
    Ugimp,
    /// GIMP with the domain stretched by the diagonal of the deformation gradient.
    Cpgimp,
    /// 1D CPDI: the domain's two end points are tracked (Gong 6.33-6.34, prefactor 1/2).
    Cpdi,
    /// CPDI1: parallelogram (parallelepiped) domain spanned by F times the initial half-vectors.
    Cpdi1,
    /// CPDI2: quadrilateral (hexahedral) domain whose corners are tracked.
    Cpdi2,
    /// Dual domain MPM: hat functions for mass and momentum, the modified gradient (3.31).
    Ddmp,
    /// DDMP with sub-points placed evenly in each point's current domain (4.5)-(4.6).
    DdmpSubpoints,
    /// Gong's improved MPM (Ch. 5, 1D): MLS velocity at the nodes, MLS density and stress at
    /// the cell centres, one-point quadrature per cell; hat functions move the points (see
    /// `solver/impm.rs`).
    Impm,
    /// Gong's improved CPDI (6.6): CPDI mass and forces with the MLS velocity map of IMPM
    /// (linear basis, cubic B-spline) at the nodes. 1D: the 1D CPDI; 2D/3D: cpdi2 (tracked
    /// corners) with the same map [proposed extension; Gong gives 1D only].
    CpdiImproved,
    /// The same improved CPDI on cpdi1's domains (the parallelogram or parallelepiped x_p +/-
    /// F r0_a, not tracked corners), 2D and 3D [proposed extension, as `cpdi-improved` there].
    Cpdi1Improved,
    /// Total-Lagrangian MPM (battery thesis 6.1, notes C.1): hat functions, their gradients and
    /// the nodal masses at the points' reference positions X_p, computed once; first
    /// Piola-Kirchhoff forces; the PIC/FLIP blend of (6.33); F updated with the re-mapped nodal
    /// velocity (see `solver/tlmpm.rs`). No point changes its stencil, so no cell crossing.
    Tlmpm,
}

impl SchemeKind {
    /// Scene names of the schemes this build implements.
    pub const NAMES: &'static [(&'static str, SchemeKind)] = &[
        ("mpm", SchemeKind::Mpm),
        ("ugimp", SchemeKind::Ugimp),
        ("cpgimp", SchemeKind::Cpgimp),
        ("cpdi", SchemeKind::Cpdi),
        ("cpdi1", SchemeKind::Cpdi1),
        ("cpdi2", SchemeKind::Cpdi2),
        ("ddmp", SchemeKind::Ddmp),
        ("ddmp-subpoints", SchemeKind::DdmpSubpoints),
        ("impm", SchemeKind::Impm),
        ("cpdi-improved", SchemeKind::CpdiImproved),
        ("cpdi1-improved", SchemeKind::Cpdi1Improved),
        ("tlmpm", SchemeKind::Tlmpm),
    ];

    pub fn from_name(name: &str) -> Option<SchemeKind> {
        Self::NAMES.iter().find(|(n, _)| *n == name).map(|(_, k)| *k)
    }

    pub fn name(self) -> &'static str {
        Self::NAMES.iter().find(|(_, k)| *k == self).map(|(n, _)| *n).unwrap_or("?")
    }

    /// Whether the scheme is defined in `dim` dimensions (`cpdi` is the 1D form; 2D and 3D
    /// name `cpdi1` or `cpdi2`; `cpdi1-improved` is the 2D/3D choice of base that 1D does not
    /// have).
    pub fn supports_dimension(self, dim: usize) -> bool {
        match self {
            SchemeKind::Cpdi => dim == 1,
            SchemeKind::Cpdi1Improved => (2..=3).contains(&dim),
            _ => (1..=3).contains(&dim),
        }
    }

    /// Whether the scheme moves the points' domain corners with the grid every step.
    pub fn tracks_corners(self) -> bool {
        matches!(self, SchemeKind::Cpdi | SchemeKind::Cpdi2 | SchemeKind::CpdiImproved)
    }

    /// Gong's improved CPDI (6.6) on either base: CPDI mass and forces, MLS nodal velocities.
    pub fn is_cpdi_improved(self) -> bool {
        matches!(self, SchemeKind::CpdiImproved | SchemeKind::Cpdi1Improved)
    }

    /// Whether the scheme maps the points' velocities to the nodes by MLS (impm and the
    /// improved CPDIs) instead of the shape functions' mass-weighted average.
    pub fn maps_velocity_by_mls(self) -> bool {
        self == SchemeKind::Impm || self.is_cpdi_improved()
    }

    /// Whether the scheme uses the modified gradient of DDMP.
    pub fn is_ddmp(self) -> bool {
        matches!(self, SchemeKind::Ddmp | SchemeKind::DdmpSubpoints)
    }
}

/// The stencil rows of one chunk of consecutive points (see [`crate::par`]).
#[derive(Debug, Clone, Default)]
pub struct StencilPart<const D: usize> {
    /// Index of the chunk's first point.
    pub first: usize,
    /// Point `first + k` owns entries `offsets[k]..offsets[k + 1]`.
    pub offsets: Vec<usize>,
    pub node: Vec<usize>,
    pub weight: Vec<f64>,
    pub grad: Vec<[f64; D]>,
    /// Nodes `lo..hi` the chunk touches.
    pub span: (usize, usize),
}

impl<const D: usize> StencilPart<D> {
    pub(crate) fn clear(&mut self, first: usize) {
        self.first = first;
        self.offsets.clear();
        self.offsets.push(0);
        self.node.clear();
        self.weight.clear();
        self.grad.clear();
        self.span = (usize::MAX, 0);
    }

    #[inline]
    pub(crate) fn push(&mut self, node: usize, w: f64, g: [f64; D]) {
        self.node.push(node);
        self.weight.push(w);
        self.grad.push(g);
        self.span = (self.span.0.min(node), self.span.1.max(node + 1));
    }

    pub(crate) fn end_point(&mut self) {
        self.offsets.push(self.node.len());
    }

    /// Entries of the chunk's `k`-th point.
    #[inline]
    pub fn entries(&self, k: usize) -> Range<usize> {
        self.offsets[k]..self.offsets[k + 1]
    }

    pub fn len(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Per-point node lists: for every point the nodes it interacts with, the weight S_ip that
/// maps mass and momentum and the gradient G_ip used for forces and the velocity gradient.
/// Stored in chunks of [`crate::par::CHUNK`] points so every pass runs chunk-parallel.
#[derive(Debug, Clone, Default)]
pub struct Stencil<const D: usize> {
    pub parts: Vec<StencilPart<D>>,
}

impl<const D: usize> Stencil<D> {
    /// Nodes, weights and gradients of point `p`.
    pub fn row(&self, p: usize) -> (&[usize], &[f64], &[[f64; D]]) {
        let part = &self.parts[p / CHUNK];
        let r = part.entries(p - part.first);
        (&part.node[r.clone()], &part.weight[r.clone()], &part.grad[r])
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.parts.iter().map(StencilPart::len).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Chunk-window of nodes touched by the points of `range` (a chunk range).
    pub fn span(&self, range: Range<usize>) -> (usize, usize) {
        let part = &self.parts[range.start / CHUNK];
        if part.span.0 > part.span.1 { (0, 0) } else { part.span }
    }
}

/// A point that the stencil cannot place on the grid (`axis` and `position` say where), or
/// whose tracked domain turned inside out (`inverted`).
#[derive(Debug, Clone, PartialEq)]
pub struct OutsideGrid {
    pub point: usize,
    pub axis: usize,
    pub position: f64,
    pub inverted: bool,
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

/// Appends point `p`'s row for the hat and GIMP schemes (tensor products of 1D factors).
pub(crate) fn gimp_row<const D: usize>(
    kind: SchemeKind,
    grid: &Grid<D>,
    pts: &Particles<D>,
    p: usize,
    out: &mut StencilPart<D>,
) -> Result<(), OutsideGrid> {
    // Per-axis 1D factors: (node index along the axis, S, dS); at most 4 per axis.
    let mut axis_terms = [[(0usize, 0.0f64, 0.0f64); 4]; D];
    let mut counts = [0usize; D];
    for a in 0..D {
        let h = grid.h[a];
        let lp = match kind {
            SchemeKind::Ugimp => pts.half_length[p][a],
            SchemeKind::Cpgimp => (pts.half_length[p][a] * pts.def_grad[p][a][a]).min(0.5 * h),
            _ => 0.0,
        };
        let xi = (pts.x[p][a] - grid.origin[a]) / h;
        let reach = if lp > 0.0 { 1.0 + lp / h } else { 1.0 };
        let lo = (xi - reach).floor() as i64;
        let hi = (xi + reach).ceil() as i64;
        // The folded part of a domain past the low face, added to the face node's entry.
        let mut folded = (0.0, 0.0);
        for i in lo..=hi {
            let r = pts.x[p][a] - (grid.origin[a] + h * i as f64);
            let (s, ds) = if lp > 0.0 { gimp(r, h, lp) } else { hat(r, h) };
            let (s, ds) = (s + folded.0, ds + folded.1);
            folded = (0.0, 0.0);
            // Round-off at the edge of the support (a domain touching the grid's boundary)
            // must not reach a node outside the grid.
            if s.abs() < 1e-12 && (ds * h).abs() < 1e-9 {
                continue;
            }
            let Some(node) = grid.wrap(a, i) else {
                // A point inside the grid whose domain pokes past a face (a point against a wall
                // or a symmetry plane, moved by round-off or pressed toward it): the weight and
                // gradient of the node beyond the face go to the face node, so the row keeps
                // its partition of unity (sum S = 1, sum G = 0: mass, momentum and diffused
                // content are mapped whole; dropping the sliver, as this did before, lost
                // content) and the face's condition acts on the material past it. A point
                // outside the grid stops the run.
                let inside = pts.x[p][a] >= grid.origin[a] && pts.x[p][a] <= grid.extent_max()[a];
                if inside && i < 0 {
                    folded = (s, ds);
                    continue;
                }
                let last = grid.cells[a];
                if inside && counts[a] > 0 && axis_terms[a][counts[a] - 1].0 == grid.wrap(a, last as i64).unwrap_or(usize::MAX) {
                    axis_terms[a][counts[a] - 1].1 += s;
                    axis_terms[a][counts[a] - 1].2 += ds;
                    continue;
                }
                return Err(OutsideGrid { point: p, axis: a, position: pts.x[p][a], inverted: false });
            };
            if counts[a] < 4 {
                axis_terms[a][counts[a]] = (node, s, ds);
                counts[a] += 1;
            }
        }
    }
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
        out.push(grid.linear(idx), w, g);
    }
    Ok(())
}

/// Linear shape functions of the grid cell holding `x`: the cell's lower node (unwrapped),
/// and for each of its `2^D` nodes (node `k` is `cell + bits of k`) the value and gradient.
#[derive(Debug, Clone, Copy)]
pub(crate) struct CellShape<const D: usize> {
    pub cell: [i64; D],
    pub s: [f64; 8],
    pub g: [[f64; D]; 8],
}

/// Cell shape functions at `x`. Along a non-periodic axis `x` is clamped into the grid (a
/// sub-point or corner of a point touching a wall), so the result is always a partition of
/// unity with gradients summing to zero.
#[inline]
pub(crate) fn cell_shape<const D: usize>(grid: &Grid<D>, x: &[f64; D]) -> CellShape<D> {
    let mut cell = [0i64; D];
    let mut xi = [0.0; D];
    for a in 0..D {
        let mut u = (x[a] - grid.origin[a]) / grid.h[a];
        let n = grid.cells[a] as f64;
        if !grid.periodic(a) {
            u = u.clamp(0.0, n);
        }
        let mut c = u.floor();
        if !grid.periodic(a) && c >= n {
            c = n - 1.0;
        }
        cell[a] = c as i64;
        xi[a] = u - c;
    }
    let mut s = [0.0; 8];
    let mut g = [[0.0; D]; 8];
    for k in 0..(1usize << D) {
        let mut w = 1.0;
        for a in 0..D {
            w *= if k >> a & 1 == 1 { xi[a] } else { 1.0 - xi[a] };
        }
        s[k] = w;
        for b in 0..D {
            let mut gb = if k >> b & 1 == 1 { 1.0 / grid.h[b] } else { -1.0 / grid.h[b] };
            for a in 0..D {
                if a != b {
                    gb *= if k >> a & 1 == 1 { xi[a] } else { 1.0 - xi[a] };
                }
            }
            g[k][b] = gb;
        }
    }
    CellShape { cell, s, g }
}

/// Unwrapped node `k` of a cell.
#[inline]
pub(crate) fn cell_node<const D: usize>(cell: &[i64; D], k: usize) -> [i64; D] {
    std::array::from_fn(|a| cell[a] + (k >> a & 1) as i64)
}

/// Linear index of an unwrapped node, `None` outside a non-periodic grid.
#[inline]
pub(crate) fn node_index<const D: usize>(grid: &Grid<D>, idx: &[i64; D]) -> Option<usize> {
    let mut lin = 0;
    for a in (0..D).rev() {
        lin = lin * grid.nodes_along(a) + grid.wrap(a, idx[a])?;
    }
    Some(lin)
}

/// A dense box of nodes (unwrapped indices `lo .. lo + dims`) accumulating one point's row.
#[derive(Debug, Clone)]
pub(crate) struct Block<const D: usize> {
    lo: [i64; D],
    dims: [usize; D],
    pub w: Vec<f64>,
    pub g: Vec<[f64; D]>,
    /// Per-node scratch coefficient (DDMP's B-term weights).
    pub c: Vec<f64>,
}

impl<const D: usize> Default for Block<D> {
    fn default() -> Self {
        Block { lo: [0; D], dims: [0; D], w: Vec::new(), g: Vec::new(), c: Vec::new() }
    }
}

impl<const D: usize> Block<D> {
    pub fn reset(&mut self, lo: [i64; D], hi: [i64; D]) {
        self.lo = lo;
        self.dims = std::array::from_fn(|a| (hi[a] - lo[a] + 1).max(0) as usize);
        let n: usize = self.dims.iter().product();
        self.w.clear();
        self.w.resize(n, 0.0);
        self.g.clear();
        self.g.resize(n, [0.0; D]);
        self.c.clear();
        self.c.resize(n, 0.0);
    }

    /// Grid index (unwrapped) of block entry `k`.
    #[inline]
    pub fn node(&self, mut k: usize) -> [i64; D] {
        std::array::from_fn(|a| {
            let c = k % self.dims[a];
            k /= self.dims[a];
            self.lo[a] + c as i64
        })
    }

    #[inline]
    pub fn index(&self, i: &[i64; D]) -> usize {
        let mut k = 0;
        for a in (0..D).rev() {
            k = k * self.dims[a] + (i[a] - self.lo[a]) as usize;
        }
        k
    }

    /// Appends the non-zero entries as point `p`'s row.
    pub fn emit(&self, grid: &Grid<D>, p: usize, x: &[f64; D], out: &mut StencilPart<D>) -> Result<(), OutsideGrid> {
        for k in 0..self.w.len() {
            let (w, g) = (self.w[k], self.g[k]);
            if w == 0.0 && g.iter().all(|v| *v == 0.0) {
                continue;
            }
            let idx = self.node(k);
            match node_index(grid, &idx) {
                Some(node) => out.push(node, w, g),
                None => {
                    let axis = (0..D).find(|&a| grid.wrap(a, idx[a]).is_none()).unwrap_or(0);
                    return Err(OutsideGrid { point: p, axis, position: x[axis], inverted: false });
                }
            }
        }
        Ok(())
    }
}

/// Corner positions of point `p`'s domain for the CPDI schemes: tracked corners (cpdi,
/// cpdi2) or the parallelepiped `x_p +/- F r0_a` (cpdi1).
pub(crate) fn domain_corners<const D: usize>(kind: SchemeKind, pts: &Particles<D>, p: usize, out: &mut [[f64; D]; 8]) {
    let nc = 1usize << D;
    if kind.tracks_corners() {
        out[..nc].copy_from_slice(&pts.corners[p * nc..(p + 1) * nc]);
    } else {
        let r: [[f64; D]; D] = std::array::from_fn(|a| pts.half_vector(p, a));
        for (k, c) in out.iter_mut().enumerate().take(nc) {
            *c = std::array::from_fn(|i| {
                let mut v = pts.x[p][i];
                for (a, ra) in r.iter().enumerate() {
                    v += if k >> a & 1 == 1 { ra[i] } else { -ra[i] };
                }
                v
            });
        }
    }
}

/// Integrals over a multilinear domain with the given corners of each corner's shape
/// function N_a and of its gradient, and the domain volume, by 2-point Gauss quadrature per
/// axis (exact for parallelepipeds and bilinear quadrilaterals). `None` when the domain is
/// inverted at a quadrature point.
pub(crate) fn corner_integrals<const D: usize>(corners: &[[f64; D]; 8]) -> Option<([f64; 8], [[f64; D]; 8], f64)> {
    let nc = 1usize << D;
    let gp = 1.0 / 3f64.sqrt();
    let (mut w, mut g, mut vol) = ([0.0; 8], [[0.0; D]; 8], 0.0);
    for q in 0..nc {
        let xi: [f64; D] = std::array::from_fn(|a| if q >> a & 1 == 1 { gp } else { -gp });
        let mut n = [0.0; 8];
        let mut dn = [[0.0; D]; 8];
        for k in 0..nc {
            let sgn = |a: usize| if k >> a & 1 == 1 { 1.0 } else { -1.0 };
            n[k] = (0..D).map(|a| 0.5 * (1.0 + sgn(a) * xi[a])).product();
            for b in 0..D {
                dn[k][b] = 0.5 * sgn(b) * (0..D).filter(|&a| a != b).map(|a| 0.5 * (1.0 + sgn(a) * xi[a])).product::<f64>();
            }
        }
        // J_ib = dx_i / dxi_b, embedded in 3x3 with identity padding.
        let mut j = crate::tensor::IDENTITY;
        for i in 0..D {
            for b in 0..D {
                j[i][b] = (0..nc).map(|k| corners[k][i] * dn[k][b]).sum();
            }
        }
        let det = crate::tensor::det(&j);
        if !(det > 0.0) {
            return None;
        }
        let inv = crate::tensor::inverse(&j)?;
        vol += det;
        for k in 0..nc {
            w[k] += n[k] * det;
            for i in 0..D {
                // (grad_x N)_i = sum_b (J^-1)_bi dN/dxi_b.
                g[k][i] += det * (0..D).map(|b| inv[b][i] * dn[k][b]).sum::<f64>();
            }
        }
    }
    Some((w, g, vol))
}

/// Appends point `p`'s CPDI row: S_ip = sum_a N_i(x_a) w_a / V, G_ip = sum_a N_i(x_a) g_a / V
/// (Gong 6.26-6.27, 6.30-6.32, 6.33-6.34 with the prefactor 1/2 of the errata).
pub(crate) fn cpdi_row<const D: usize>(
    kind: SchemeKind,
    grid: &Grid<D>,
    pts: &Particles<D>,
    p: usize,
    block: &mut Block<D>,
    out: &mut StencilPart<D>,
) -> Result<(), OutsideGrid> {
    let nc = 1usize << D;
    let mut corners = [[0.0; D]; 8];
    domain_corners(kind, pts, p, &mut corners);
    let inverted = OutsideGrid { point: p, axis: 0, position: pts.x[p][0], inverted: true };
    let (w, g, vol) = corner_integrals(&corners).ok_or(inverted)?;
    let shapes: [CellShape<D>; 8] = std::array::from_fn(|k| cell_shape(grid, &corners[k.min(nc - 1)]));
    let lo: [i64; D] = std::array::from_fn(|a| shapes[..nc].iter().map(|s| s.cell[a]).min().unwrap_or(0));
    let hi: [i64; D] = std::array::from_fn(|a| shapes[..nc].iter().map(|s| s.cell[a]).max().unwrap_or(0) + 1);
    block.reset(lo, hi);
    for (k, sh) in shapes[..nc].iter().enumerate() {
        for m in 0..nc {
            let b = block.index(&cell_node(&sh.cell, m));
            let n = sh.s[m];
            block.w[b] += n * w[k] / vol;
            for i in 0..D {
                block.g[b][i] += n * g[k][i] / vol;
            }
        }
    }
    block.emit(grid, p, &pts.x[p], out)
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
