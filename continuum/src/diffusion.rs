//! Scalar diffusion carried by the material points (a temperature, or a normalised lithium
//! concentration): battery thesis (6.3)-(6.10) and (7.5)-(7.8), with the sign and shape-function
//! errata fixed (wave2 notes C.2, C.3).
//!
//! Every point carries c_p and a capacity V0_p (its reference volume: unit rho0 C, or the host
//! volume that holds the lithium), so its content is V0_p c_p and the total is conserved.
//!
//! **Current configuration** (the default): each step on the solver's stencil at x^n,
//! - C*_i = sum_p S_ip V0_p and c_i = sum_p S_ip V0_p c_p / C*_i (6.3)-(6.5);
//! - the flux q_p = -K sum_i G_ip c_i (6.10 with its minus sign) and
//!   Q_i = sum_p V_p q_p . G_ip (6.6), V_p the current volume;
//! - c_dot_i = (Q_i + S_i) / C*_i with S_i the boundary source; c_p += dt sum_i S_ip c_dot_i
//!   (6.9 with its S_ip), blended with PIC by the FLIP fraction beta (6.16 with its S_cp):
//!   c_p = beta (c_p + dt sum S c_dot) + (1 - beta) sum S (c_i + dt c_dot_i).
//!
//! **Reference configuration** (C.3, 6.67-6.75 with the sign fixed): the stencil is built once
//! at the points' reference positions x0 (their positions at the start), the nodal values are
//! kept from step to step (c_i += dt c_dot_i), Q_i = sum_p V0_p Q_p . G0_ip with
//! Q_p = -K0 G0 c, K0 = K J C^-1 (6.71-6.72; K / J in 1D).
//!
//! **Under tlmpm** ([`Configuration::Lagrangian`], which the solver selects for the scheme
//! `Tlmpm`): the same reference form on the solver's own stencil at X_p, but the nodal values
//! projected from the points every step, as tlmpm re-maps its nodal velocity (6.34): the points
//! carry the whole state, so a checkpoint of them resumes bit for bit, and both Dirichlet modes
//! apply. (Carrying the nodal values, as the library form does, would make them state a resume
//! has to restore; projected, they are a function of the points.)
//!
//! Sources on the points ([`Diffusion::surface_source`], battery thesis (7.16)-(7.18)): a
//! surface point's j A_p, times the saturation factor, enters the nodes as
//! S_i = sum_p S_ip j A_p f(c_p) and is counted in the boundary content.
//!
//! Conservation: sum_i G_ip = 0 (partition of unity), so the total content changes by exactly
//! the boundary source (Dirichlet nodes' imposed rates and the face fluxes), to round-off
//! ([`Diffusion::boundary_content`]).
//!
//! Stability (C.3 corrected): in the reference form, uniform J and hats with symmetric points,
//! the checkerboard's amplification is G = 1 - 4 dt K / (J h0^2), so dt <= J h0^2 / (2 K); for
//! varying J the sufficient bound is dt <= J_min h0^2 / (2 d K) in d dimensions
//! ([`explicit_bound`]). In the current form on a fixed grid a point at J spans h0 = h / J of
//! its reference length per cell, so the same bound reads h^2 / (2 d K J_max); the FLIP
//! re-projection of the current form is more stable than that (it is sufficient there).

use crate::grid::Grid;
use crate::par::CHUNK;
use crate::particles::Particles;
use crate::shape::{self, OutsideGrid, SchemeKind, Stencil, StencilPart};
use crate::tensor::{self, Mat3};

/// A condition on one grid face (absent: no flux through it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FaceCondition {
    /// The nodal value on the face is held at this value.
    Dirichlet(f64),
    /// This flux into the body through the face (content per unit face area per second:
    /// K times a concentration gradient, m/s for a normalised concentration).
    Flux(f64),
}

/// How a Dirichlet face reaches the points.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum DirichletMode {
    /// On the nodal rate: c_dot_i = (c_bc - c_i) / dt at the face's nodes, so the FLIP update
    /// carries the boundary value to the points near the face (the default).
    #[default]
    Rate,
    /// On the nodal value only: c_i = c_bc for the gradients, c_dot_i = 0; the outer layer of
    /// points does not receive the boundary value (the "nullspace layer" of B Fig. 6.1).
    Value,
}

/// Where the diffusion is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Configuration {
    /// On the solver's stencil at x^n with K and the current volumes V (the default).
    #[default]
    Current,
    /// On a stencil of its own at x0, built once, with K0 = K J C^-1 and V0, the nodal values
    /// carried from step to step (the library form of C.3; Dirichlet on the value).
    Reference,
    /// The reference form on the solver's own stencil, which is at the reference positions
    /// X_p (`tlmpm`): K0 = K J C^-1 (6.71-6.72) and V0 (6.73), the nodal values projected from
    /// the points every step as the current form does and as tlmpm re-maps its velocities
    /// (6.34), so the points carry everything (a checkpoint of them resumes bit for bit), and
    /// either Dirichlet mode applies.
    Lagrangian,
}

/// How the diffusivity of a point depends on its state: K times [`DiffusivityLaw::factor`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum DiffusivityLaw {
    /// K everywhere.
    #[default]
    Constant,
    /// K exp(alpha c - beta p) with the pressure p = -tr(sigma)/3 (Pa) clamped to
    /// [-p_max, p_max] (battery thesis Ch. 7.3: alpha 6, beta 0.5 /GPa, p_max 3 GPa; the clamp
    /// on both sides is this code's choice: it bounds the factor, and so the explicit step).
    Pressure { alpha: f64, beta: f64, p_max: f64 },
    /// K (1 - c)^3 with c clamped to [0, 1] (the thesis's alternative: diffusion stops at
    /// saturation).
    Cubic,
}

impl DiffusivityLaw {
    /// The factor on K at concentration `c` and pressure `p` (Pa).
    pub fn factor(&self, c: f64, p: f64) -> f64 {
        match *self {
            DiffusivityLaw::Constant => 1.0,
            DiffusivityLaw::Pressure { alpha, beta, p_max } => (alpha * c - beta * p.clamp(-p_max, p_max)).exp(),
            DiffusivityLaw::Cubic => (1.0 - c.clamp(0.0, 1.0)).powi(3),
        }
    }

    /// The largest factor over c in [0, 1] and any pressure (for the explicit bound).
    pub fn max_factor(&self) -> f64 {
        match *self {
            DiffusivityLaw::Constant | DiffusivityLaw::Cubic => 1.0,
            DiffusivityLaw::Pressure { alpha, beta, p_max } => (alpha.max(0.0) + beta.abs() * p_max).exp(),
        }
    }
}

/// The diffusion of one scalar field over every point of a simulation.
#[derive(Debug, Clone)]
pub struct Diffusion<const D: usize> {
    /// Diffusivity K (m^2/s): k / (rho0 C) for heat, D for a concentration.
    pub diffusivity: f64,
    /// How the diffusivity depends on the point's concentration and pressure.
    pub law: DiffusivityLaw,
    /// (min face, max face) per axis.
    pub faces: [(Option<FaceCondition>, Option<FaceCondition>); D],
    pub dirichlet: DirichletMode,
    /// FLIP fraction beta of the point update (1: FLIP, 0: PIC).
    pub flip: f64,
    pub configuration: Configuration,
    /// Content added through the faces since the start (sum of V0 c units).
    pub boundary_content: f64,
    /// Total content at the first step.
    pub initial_content: f64,
    /// Nodal values of the last step (after the Dirichlet values), for output and error measures.
    pub node_value: Vec<f64>,
    /// Nodal capacities C*_i of the last step.
    pub node_capacity: Vec<f64>,
    node_flux: Vec<f64>,
    node_rate: Vec<f64>,
    node_content: Vec<f64>,
    reference_stencil: Option<Stencil<D>>,
    /// Reference form: nodal values carried between steps.
    carried: bool,
    /// The points that carry the field (empty: every point). The others take no part: no
    /// capacity, no flux, no update (a substrate that holds no lithium); the field ends where
    /// they begin, a no-flux boundary.
    pub active: Vec<bool>,
    /// Per point, the content per second its exposed surface takes in (j A_p, battery thesis
    /// (7.16): a flux j on the area A_p the point exposes at t = 0), times the saturation factor
    /// clamp(1 + 0.25 ln(1 - c_p), 0, 1) of (7.17); mapped to the nodes as a source
    /// (7.18, S_ip-weighted). Empty: none.
    pub surface_source: Vec<f64>,
    node_source: Vec<f64>,
}

/// The saturation factor of the surface flux (battery thesis (7.17), natural log, clamped to
/// [0, 1]: 1 at c = 0, 0 from c = 1 - e^-4 = 0.9817 on).
pub fn saturation_factor(c: f64) -> f64 {
    if c >= 1.0 { 0.0 } else { (1.0 + 0.25 * (1.0 - c).ln()).clamp(0.0, 1.0) }
}

/// The area each point exposes at t = 0 (battery thesis 7.1.3: surface points and their areas
/// are found once): the points lie on the scene's regular lattice of `2 half_length` spacing;
/// a face of an `include`d point is exposed where the lattice site beyond it holds no point
/// (of any body) and lies inside the grid (a face against a grid wall or a symmetry plane is
/// not exposed). The area of a face is the product of the point's widths along the other axes
/// (2D: per unit depth). Points not included get 0.
pub fn exposed_areas<const D: usize>(grid: &Grid<D>, pts: &Particles<D>, include: &[bool]) -> Vec<f64> {
    use std::collections::HashSet;
    let n = pts.len();
    let key = |p: usize, a_shift: Option<(usize, i64)>| -> [i64; D] {
        std::array::from_fn(|a| {
            let w = 2.0 * pts.half_length[p][a];
            let k = ((pts.x0[p][a] - grid.origin[a]) / w - 0.5).round() as i64;
            match a_shift {
                Some((b, s)) if b == a => k + s,
                _ => k,
            }
        })
    };
    let occupied: HashSet<[i64; D]> = (0..n).map(|p| key(p, None)).collect();
    (0..n)
        .map(|p| {
            if !include.get(p).copied().unwrap_or(true) {
                return 0.0;
            }
            let mut area = 0.0;
            for a in 0..D {
                let w = 2.0 * pts.half_length[p][a];
                let face: f64 = (0..D).filter(|&b| b != a).map(|b| 2.0 * pts.half_length[p][b]).product();
                for s in [-1i64, 1] {
                    let beyond = pts.x0[p][a] + s as f64 * w;
                    let hi = grid.origin[a] + grid.cells[a] as f64 * grid.h[a];
                    let inside = beyond > grid.origin[a] && beyond < hi;
                    if inside && !occupied.contains(&key(p, Some((a, s)))) {
                        area += face;
                    }
                }
            }
            area
        })
        .collect()
}

impl<const D: usize> Diffusion<D> {
    pub fn new(diffusivity: f64, faces: [(Option<FaceCondition>, Option<FaceCondition>); D]) -> Self {
        Diffusion {
            diffusivity,
            law: DiffusivityLaw::Constant,
            faces,
            dirichlet: DirichletMode::Rate,
            flip: 1.0,
            configuration: Configuration::Current,
            boundary_content: 0.0,
            initial_content: f64::NAN,
            node_value: Vec::new(),
            node_capacity: Vec::new(),
            node_flux: Vec::new(),
            node_rate: Vec::new(),
            node_content: Vec::new(),
            reference_stencil: None,
            carried: false,
            active: Vec::new(),
            surface_source: Vec::new(),
            node_source: Vec::new(),
        }
    }

    /// Total content sum_p V0_p c_p.
    pub fn content(pts: &Particles<D>) -> f64 {
        pts.volume0.iter().zip(&pts.scalar).map(|(v, c)| v * c).sum()
    }

    /// Content sum_p V0_p c_p over the points that carry the field ([`Diffusion::active`]).
    pub fn active_content(&self, pts: &Particles<D>) -> f64 {
        (0..pts.len()).filter(|&p| self.is_active(p)).map(|p| pts.volume0[p] * pts.scalar[p]).sum()
    }

    fn is_active(&self, p: usize) -> bool {
        self.active.get(p).copied().unwrap_or(true)
    }

    /// Sets the nodal values the reference form carries (otherwise projected from the points
    /// at its first step).
    pub fn set_node_values(&mut self, values: Vec<f64>) {
        self.node_value = values;
        self.carried = true;
    }

    /// The face condition of node `idx` along the axes where it lies on a face: the first
    /// Dirichlet face wins; the flux faces' sources are summed into `flux_area`.
    fn node_conditions(&self, grid: &Grid<D>, idx: [usize; D]) -> (Option<f64>, f64) {
        let mut dirichlet = None;
        let mut source = 0.0;
        for a in 0..D {
            let last = grid.nodes_along(a) - 1;
            for (on, cond) in [(idx[a] == 0, self.faces[a].0), (idx[a] == last, self.faces[a].1)] {
                if !on || grid.periodic(a) {
                    continue;
                }
                match cond {
                    Some(FaceCondition::Dirichlet(v)) => dirichlet = dirichlet.or(Some(v)),
                    Some(FaceCondition::Flux(j)) => {
                        // The face area a node stands for: h along the other axes, half at an edge.
                        let mut area = 1.0;
                        for b in (0..D).filter(|&b| b != a) {
                            let n = grid.nodes_along(b) - 1;
                            area *= if idx[b] == 0 || idx[b] == n { 0.5 * grid.h[b] } else { grid.h[b] };
                        }
                        source += j * area;
                    }
                    None => {}
                }
            }
        }
        (dirichlet, source)
    }

    /// One explicit step of `dt` at time `time` on `stencil` (the solver's, at x^n; ignored in
    /// the reference form): writes every point's rate into `scalar_rate` (added to what is there)
    /// and advances `scalar`.
    pub fn step(
        &mut self,
        grid: &Grid<D>,
        scheme: SchemeKind,
        stencil: &Stencil<D>,
        pts: &mut Particles<D>,
        dt: f64,
    ) -> Result<(), OutsideGrid> {
        let n_nodes = grid.node_count();
        let reference = self.configuration == Configuration::Reference;
        // Both reference forms: K0 and V0 on a stencil at X_p.
        let total = reference || self.configuration == Configuration::Lagrangian;
        if reference && self.reference_stencil.is_none() {
            self.reference_stencil = Some(stencil_at_x0(scheme, grid, pts)?);
        }
        let st = if reference { self.reference_stencil.as_ref().unwrap_or(stencil) } else { stencil };
        for v in [&mut self.node_capacity, &mut self.node_flux, &mut self.node_rate, &mut self.node_content, &mut self.node_source] {
            v.clear();
            v.resize(n_nodes, 0.0);
        }
        let n = pts.len();
        if self.initial_content.is_nan() {
            self.initial_content = self.active_content(pts);
        }
        for p in 0..n {
            if !self.is_active(p) {
                continue;
            }
            let (nodes, w, _) = st.row(p);
            let src = self.surface_source.get(p).map_or(0.0, |j| j * saturation_factor(pts.scalar[p]));
            for (&i, &s) in nodes.iter().zip(w) {
                self.node_capacity[i] += s * pts.volume0[p];
                self.node_content[i] += s * pts.volume0[p] * pts.scalar[p];
                if src != 0.0 {
                    self.node_source[i] += s * src;
                }
            }
        }
        let floor = 1e-12 * pts.volume0.iter().cloned().fold(f64::INFINITY, f64::min);
        // Projected nodal values c_i^proj (6.5).
        let projected: Vec<f64> =
            (0..n_nodes).map(|i| if self.node_capacity[i] > floor { self.node_content[i] / self.node_capacity[i] } else { 0.0 }).collect();
        if !(reference && self.carried && self.node_value.len() == n_nodes) {
            self.node_value = projected.clone();
        }
        self.carried = reference;
        let conditions: Vec<(Option<f64>, f64)> = (0..n_nodes).map(|i| self.node_conditions(grid, grid.unlinear(i))).collect();
        let value_mode = self.dirichlet == DirichletMode::Value || reference;
        if value_mode {
            for (i, (d, _)) in conditions.iter().enumerate() {
                if let Some(v) = d {
                    self.node_value[i] = *v;
                }
            }
        }
        // Fluxes Q_i = sum_p V q_p . G_ip with q_p = -K grad c (current) or -K0 grad0 c (reference).
        for p in 0..n {
            if !self.is_active(p) {
                continue;
            }
            let (nodes, _, grads) = st.row(p);
            let mut g = [0.0; D];
            for (&i, gi) in nodes.iter().zip(grads) {
                for a in 0..D {
                    g[a] += gi[a] * self.node_value[i];
                }
            }
            let k = match self.law {
                DiffusivityLaw::Constant => self.diffusivity,
                law => self.diffusivity * law.factor(pts.scalar[p], pts.pressure(p)),
            };
            let q: [f64; D] = if total {
                let k0 = reference_conductivity(&pts.def_grad[p], k);
                std::array::from_fn(|a| -(0..D).map(|b| k0[a][b] * g[b]).sum::<f64>())
            } else {
                std::array::from_fn(|a| -k * g[a])
            };
            let vol = if total { pts.volume0[p] } else { pts.volume[p] };
            for (&i, gi) in nodes.iter().zip(grads) {
                self.node_flux[i] += vol * (0..D).map(|a| q[a] * gi[a]).sum::<f64>();
            }
        }
        let mut source = 0.0;
        for i in 0..n_nodes {
            let (dirichlet, face_in) = conditions[i];
            let flux_in = face_in + self.node_source[i];
            let cap = self.node_capacity[i];
            let rate = match dirichlet {
                Some(_) if value_mode => 0.0,
                Some(v) => (v - projected[i]) / dt,
                None if cap > floor => (self.node_flux[i] + flux_in) / cap,
                None => 0.0,
            };
            self.node_rate[i] = rate;
            if cap > floor {
                if dirichlet.is_some() {
                    // What the Dirichlet node adds beyond the fluxes its points exchange.
                    source += dt * (cap * rate - self.node_flux[i]);
                    if !reference {
                        source += (1.0 - self.flip) * cap * (self.node_value[i] - projected[i]);
                    }
                } else {
                    source += dt * flux_in;
                }
            }
        }
        self.boundary_content += source;
        let beta = self.flip;
        for p in 0..n {
            if !self.is_active(p) {
                continue;
            }
            let (nodes, w, _) = st.row(p);
            let (mut inc, mut pic) = (0.0, 0.0);
            for (&i, &s) in nodes.iter().zip(w) {
                inc += s * self.node_rate[i];
                pic += s * (self.node_value[i] + dt * self.node_rate[i]);
            }
            let old = pts.scalar[p];
            let new = if beta == 1.0 { old + dt * inc } else { beta * (old + dt * inc) + (1.0 - beta) * pic };
            pts.scalar[p] = new;
            pts.scalar_rate[p] += (new - old) / dt;
        }
        if reference {
            for i in 0..n_nodes {
                self.node_value[i] += dt * self.node_rate[i];
            }
        }
        Ok(())
    }
}

/// K0 = K J C^-1 (6.71-6.72), in the first `D` axes.
fn reference_conductivity(f: &Mat3, k: f64) -> Mat3 {
    let j = tensor::det(f);
    let c = tensor::mul(&tensor::transpose(f), f);
    let inv = tensor::inverse(&c).unwrap_or(tensor::IDENTITY);
    tensor::add_scaled(&tensor::ZERO, &inv, k * j)
}

/// The stencil of the points at their reference positions x0 (hats and GIMP only).
fn stencil_at_x0<const D: usize>(scheme: SchemeKind, grid: &Grid<D>, pts: &Particles<D>) -> Result<Stencil<D>, OutsideGrid> {
    let mut at = pts.clone();
    at.x = pts.x0.clone();
    at.def_grad = vec![tensor::IDENTITY; pts.len()];
    let kind = match scheme {
        SchemeKind::Mpm | SchemeKind::Ugimp | SchemeKind::Cpgimp => scheme,
        _ => SchemeKind::Ugimp,
    };
    let mut stencil = Stencil::default();
    for r in crate::par::chunk_ranges(pts.len()) {
        let mut part = StencilPart::default();
        part.clear(r.start);
        for p in r {
            shape::gimp_row(kind, grid, &at, p, &mut part)?;
            part.end_point();
        }
        stencil.parts.push(part);
    }
    debug_assert!(stencil.parts.iter().all(|p| p.len() <= CHUNK));
    Ok(stencil)
}

/// The corrected explicit bound of the diffusion step (battery thesis (6.90), sign fixed, in
/// `d` dimensions): dt <= J_min h0^2 / (2 d K), with h0 the smallest reference length of a
/// cell. Given the grid spacing `h` of the current configuration and the points' J, a point
/// at J spans h0 = h / J, so this is h^2 / (2 d K J_max).
pub fn explicit_bound(h: f64, dimension: usize, diffusivity: f64, j_max: f64) -> f64 {
    h * h / (2.0 * dimension as f64 * diffusivity * j_max.max(f64::MIN_POSITIVE))
}

/// The exact solution of c_t = K c_xx on [0, l] with c(x, 0) = c0, c(0) = cl, c(l) = cr
/// (B 6.95, Fourier series), `terms` terms.
pub fn heat_series(x: f64, t: f64, l: f64, k: f64, (c0, cl, cr): (f64, f64, f64), terms: usize) -> f64 {
    let mut v = cl + (cr - cl) * x / l;
    for j in 1..=terms {
        let lam = j as f64 * std::f64::consts::PI / l;
        let sign = if j % 2 == 0 { 1.0 } else { -1.0 };
        v += 2.0 * ((c0 - cl) - (c0 - cr) * sign) / (j as f64 * std::f64::consts::PI) * (-k * lam * lam * t).exp() * (lam * x).sin();
    }
    v
}

/// The exact solution of c_t = K (c_xx + c_yy) on the rectangle [0, lx] x [0, ly] with
/// c(x, y, 0) = c0 and c = c1 on all four sides (B 6.98, K restored in the exponent):
/// c = c1 + 16 (c0 - c1) / pi^2 sum_{i, j odd} exp(-pi^2 K t (i^2/lx^2 + j^2/ly^2))
/// sin(i pi x / lx) sin(j pi y / ly) / (i j), over the odd i, j up to `terms`.
/// It is the product of two 1D series (the 1D solution from c0 with both faces at c1 is
/// c1 + 4 (c0 - c1) / pi sum_{i odd} e^{-pi^2 K t i^2 / l^2} sin(i pi x / l) / i), which is how
/// it is summed: O(terms) work, not O(terms^2).
pub fn heat_series_2d(x: [f64; 2], t: f64, l: [f64; 2], k: f64, (c0, c1): (f64, f64), terms: usize) -> f64 {
    let pi = std::f64::consts::PI;
    let axis = |a: usize| -> f64 {
        (1..=terms)
            .step_by(2)
            .map(|i| {
                let i = i as f64;
                (-pi * pi * k * t * i * i / (l[a] * l[a])).exp() * (i * pi * x[a] / l[a]).sin() / i
            })
            .sum()
    };
    c1 + 16.0 * (c0 - c1) / (pi * pi) * axis(0) * axis(1)
}
