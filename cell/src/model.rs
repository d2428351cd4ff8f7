//! The finite-volume discretisation of the full cell (battery thesis Ch. 8, with the errata of
//! the crate README): unknowns per cell `p` (cations), `n` (electrons in an electrode, anions in
//! the electrolyte) and `phi`, interleaved `[p0, n0, phi0, p1, ...]` so the Jacobian is banded.
//!
//! Units: nm, s, V, concentrations 1/nm^3, fluxes 1/(nm^2 s). The residual of cell i is
//! `p_i' = (F_p[i] - F_p[i+1]) / dx`, `n_i' = (F_n[i] - F_n[i+1]) / dx` and the algebraic
//! Poisson row `0 = (eps0/e) (G[i+1] - G[i]) / dx + p_i - n_i` (in 1/nm^3), with `F[f]` the
//! flux in +x through face f (face f lies between cells f-1 and f) and `G[f] = eps_r dphi/dx`
//! there.

use crate::scene::{CellScene, ElectronRows, FaceState, Switch};

pub use crate::units::{CM2_PER_S, E_CHARGE, EPS0, K_B};

/// Material of a cell.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Region {
    Anode,
    Electrolyte,
    Cathode,
}

impl Region {
    pub fn is_electrode(self) -> bool {
        self != Region::Electrolyte
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Right {
    /// No cation flux, zero field, electrons leave at the boundary's current (a cathode).
    Insulating,
    /// phi and p (and n) fixed at the face: a bulk electrolyte beyond it.
    Reservoir { phi: f64, p: f64, n: f64 },
}

/// The discretised cell.
#[derive(Debug, Clone)]
pub struct Model {
    /// Cells.
    pub n: usize,
    /// Cell size (nm).
    pub dx: f64,
    /// Cell centres (nm).
    pub x: Vec<f64>,
    pub region: Vec<Region>,
    /// Relative permittivity at each face (n + 1): the cells' value, the mean of the two at an
    /// interface face (8.58)-(8.59).
    pub eps_face: Vec<f64>,
    /// Relative permittivity per cell.
    pub eps: Vec<f64>,
    /// Cation diffusivity per cell (nm^2/s).
    pub d_p: Vec<f64>,
    /// Anion diffusivity per cell (nm^2/s; 0 in electrodes).
    pub d_n: Vec<f64>,
    /// Electronic conductivity per cell as a number flux per field, sigma/e (1/(V nm s); 0 in
    /// the electrolyte).
    pub sigma: Vec<f64>,
    /// Faces with the threshold law (electrode/electrolyte), in order.
    pub interfaces: Vec<usize>,
    /// Thermal voltage kT/e (V).
    pub vt: f64,
    /// eps0/e (1/(V nm)): Poisson rows in concentration units.
    pub k_poisson: f64,
    pub face_state: FaceState,
    /// The form of the electrode electron rows in [`Model::newton_rhs`].
    pub electron_rows: ElectronRows,
    /// Whether the banded LU makes its Newton corrections charge-exact (where valid, see
    /// [`Model::invariants`]).
    pub charge_exact_solve: bool,
    pub alpha: f64,
    pub threshold: f64,
    pub hysteresis: f64,
    /// What the switch compares with the thresholds is |dphi| times this: 1 (the thesis's
    /// one-face jump) or threshold_width_nm / dx (the drop over that width).
    pub jump_scale: f64,
    /// Some(width): the continuous ramp switch instead of events.
    pub ramp: Option<f64>,
    /// Dirichlet potential at x = 0 (V).
    pub phi_left: f64,
    /// Electron number flux in +x at both ends (1/(nm^2 s)), where the end cell is an electrode.
    pub electron_flux: f64,
    pub right: Right,
    /// Initial p and n per cell (phi is solved from them).
    pub p0: Vec<f64>,
    pub n0: Vec<f64>,
}

/// Per-face fluxes and the permittivity-weighted field, for diagnostics.
pub struct Faces {
    pub f_p: Vec<f64>,
    pub f_n: Vec<f64>,
    pub g: Vec<f64>,
}

/// The van Leer limited slope of a cell from its one-sided differences a, b:
/// `(p_i - p_i-1) psi(r)` with psi(r) = (r + |r|)/(1 + |r|), r = b/a, written symmetrically as
/// 2ab/(a + b) when a and b have the same sign and 0 otherwise (psi = 0 at a = 0).
#[inline]
pub fn van_leer(a: f64, b: f64) -> f64 {
    if a * b > 0.0 { 2.0 * a * b / (a + b) } else { 0.0 }
}

impl Model {
    pub fn new(scene: &CellScene) -> Model {
        let n = scene.grid.cells;
        let length = scene.length_nm();
        let dx = length / n as f64;
        let kt = K_B * scene.physics.temperature_k;
        let vt = kt / E_CHARGE;
        let mut region = Vec::with_capacity(n);
        let (mut eps, mut d_p, mut d_n, mut sigma, mut p0, mut n0) = (vec![], vec![], vec![], vec![], vec![], vec![]);
        let sigma_num = |s_per_m: f64| s_per_m / E_CHARGE * 1e-9;
        let mut push = |r: Region, count: usize, e: f64, dp: f64, dn: f64, s: f64, p: f64, c: f64| {
            for _ in 0..count {
                region.push(r);
                eps.push(e);
                d_p.push(dp);
                d_n.push(dn);
                sigma.push(s);
                p0.push(p);
                n0.push(c);
            }
        };
        let cells_of = |w: f64| (w / dx).round() as usize;
        let mut used = 0;
        if let Some(a) = &scene.anode {
            let k = cells_of(a.width_nm);
            push(Region::Anode, k, a.eps_r, a.d_p_cm2_per_s * CM2_PER_S, 0.0, sigma_num(a.sigma_s_per_m), a.p0_per_nm3, a.n0_per_nm3);
            used += k;
        }
        let el = &scene.electrolyte;
        let k_el = if scene.cathode.is_some() { cells_of(el.width_nm) } else { n - used };
        push(
            Region::Electrolyte,
            k_el,
            el.eps_r,
            el.d_p_cm2_per_s * CM2_PER_S,
            el.d_n_cm2_per_s * CM2_PER_S,
            0.0,
            el.p0_per_nm3,
            el.n0_per_nm3,
        );
        used += k_el;
        if let Some(c) = &scene.cathode {
            let k = n - used;
            push(Region::Cathode, k, c.eps_r, c.d_p_cm2_per_s * CM2_PER_S, 0.0, sigma_num(c.sigma_s_per_m), c.p0_per_nm3, c.n0_per_nm3);
        }
        let mut eps_face = vec![0.0; n + 1];
        eps_face[0] = eps[0];
        eps_face[n] = eps[n - 1];
        let mut interfaces = Vec::new();
        for f in 1..n {
            eps_face[f] = if region[f - 1] == region[f] { eps[f] } else { 0.5 * (eps[f - 1] + eps[f]) };
            if region[f - 1] != region[f] {
                interfaces.push(f);
            }
        }
        let right = match scene.boundary.right.as_str() {
            "reservoir" => Right::Reservoir { phi: scene.boundary.phi_right_v, p: el.p0_per_nm3, n: el.n0_per_nm3 },
            _ => Right::Insulating,
        };
        // 1 mA/cm^2 = 1e-3 A / (1e14 nm^2) / e.
        let electron_flux = scene.boundary.electron_current_ma_per_cm2 * 1e-3 / E_CHARGE / 1e14;
        Model {
            n,
            dx,
            x: (0..n).map(|i| (i as f64 + 0.5) * dx).collect(),
            region,
            eps_face,
            eps,
            d_p,
            d_n,
            sigma,
            interfaces,
            vt,
            k_poisson: EPS0 / E_CHARGE,
            face_state: scene.scheme.face_state,
            electron_rows: scene.scheme.electron_rows,
            charge_exact_solve: scene.scheme.charge_exact_solve,
            alpha: scene.interface.alpha,
            threshold: scene.interface.threshold_v,
            hysteresis: scene.interface.hysteresis_v,
            jump_scale: scene.interface.threshold_width_nm.map_or(1.0, |w| w / dx),
            ramp: (scene.interface.switch == Switch::Ramp).then_some(scene.interface.ramp_width_v),
            phi_left: scene.boundary.phi_left_v,
            electron_flux,
            right,
            p0,
            n0,
        }
    }

    /// Unknowns (3 per cell).
    pub fn len(&self) -> usize {
        3 * self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The consistent initial state: p0, n0 and phi from the Poisson equation.
    pub fn initial_state(&self) -> Vec<f64> {
        let mut y = vec![0.0; self.len()];
        for i in 0..self.n {
            y[3 * i] = self.p0[i];
            y[3 * i + 1] = self.n0[i];
        }
        self.solve_poisson(&mut y);
        y
    }

    /// Initial switch states: open where the switch's drop ([`Model::switch_drop`]) >= threshold.
    pub fn initial_open(&self, y: &[f64]) -> Vec<bool> {
        self.interfaces.iter().map(|&f| self.switch_drop(y, f) >= self.threshold).collect()
    }

    /// The potential drop the switch of interface face `f` compares with its thresholds.
    pub fn switch_drop(&self, y: &[f64], f: usize) -> f64 {
        (y[3 * (f - 1) + 2] - y[3 * f + 2]).abs() * self.jump_scale
    }

    /// The limited slope of species `var` (0: p, 1: n) in cell i; 0 at the domain ends, next to
    /// another material, and for the first-order face states.
    #[inline]
    fn slope(&self, y: &[f64], i: usize, var: usize) -> f64 {
        if self.face_state != FaceState::VanLeer || i == 0 || i + 1 >= self.n {
            return 0.0;
        }
        let r = self.region[i];
        if self.region[i - 1] != r || self.region[i + 1] != r {
            return 0.0;
        }
        let c = y[3 * i + var];
        van_leer(c - y[3 * (i - 1) + var], y[3 * (i + 1) + var] - c)
    }

    /// The face value of species `var` between cells a = f-1 and b = f for drift velocity v.
    #[inline]
    fn face_value(&self, y: &[f64], f: usize, var: usize, v: f64) -> f64 {
        let (ca, cb) = (y[3 * (f - 1) + var], y[3 * f + var]);
        match self.face_state {
            FaceState::Central => 0.5 * (ca + cb),
            FaceState::Upwind => {
                if v > 0.0 {
                    ca
                } else {
                    cb
                }
            }
            FaceState::VanLeer => {
                if v > 0.0 {
                    ca + 0.5 * self.slope(y, f - 1, var)
                } else {
                    cb - 0.5 * self.slope(y, f, var)
                }
            }
        }
    }

    /// Fluxes in +x through face f (cations, n species) and G = eps_r dphi/dx there.
    #[inline]
    fn face(&self, y: &[f64], open: &[bool], f: usize) -> (f64, f64, f64) {
        let n = self.n;
        let dx = self.dx;
        if f == 0 {
            let g = self.eps_face[0] * (y[2] - self.phi_left) / (0.5 * dx);
            let f_n = if self.region[0].is_electrode() { self.electron_flux } else { 0.0 };
            return (0.0, f_n, g);
        }
        if f == n {
            let last = n - 1;
            return match self.right {
                Right::Insulating => {
                    let f_n = if self.region[last].is_electrode() { self.electron_flux } else { 0.0 };
                    (0.0, f_n, 0.0)
                }
                Right::Reservoir { phi, p, n: nb } => {
                    let h = 0.5 * dx;
                    let dphi = phi - y[3 * last + 2];
                    let g = self.eps_face[n] * dphi / h;
                    let d = self.d_p[last];
                    let v = -(d / self.vt) * dphi / h;
                    let pf = if v > 0.0 { y[3 * last] } else { p };
                    let f_p = -d * (p - y[3 * last]) / h + v * pf;
                    let dn = self.d_n[last];
                    let f_n = if dn > 0.0 {
                        let vn = (dn / self.vt) * dphi / h;
                        let nf = if vn > 0.0 { y[3 * last + 1] } else { nb };
                        -dn * (nb - y[3 * last + 1]) / h + vn * nf
                    } else {
                        0.0
                    };
                    (f_p, f_n, g)
                }
            };
        }
        let (a, b) = (f - 1, f);
        let dphi = y[3 * b + 2] - y[3 * a + 2];
        let g = self.eps_face[f] * dphi / dx;
        if self.region[a] == self.region[b] {
            let d = self.d_p[a];
            let v = -(d / self.vt) * dphi / dx;
            let f_p = -d * (y[3 * b] - y[3 * a]) / dx + v * self.face_value(y, f, 0, v);
            let f_n = if self.region[a].is_electrode() {
                // Electrons drift up the potential: j_n = sigma dphi/dx (8.56).
                self.sigma[a] * dphi / dx
            } else if self.d_n[a] > 0.0 {
                let dn = self.d_n[a];
                let vn = (dn / self.vt) * dphi / dx;
                -dn * (y[3 * b + 1] - y[3 * a + 1]) / dx + vn * self.face_value(y, f, 1, vn)
            } else {
                0.0
            };
            (f_p, f_n, g)
        } else {
            // An interface: no electrons or anions cross (8.60)-(8.61); cations by the
            // threshold law (8.23) with the mean diffusivity, when the switch is open.
            let k = self.interfaces.binary_search(&f).unwrap_or(0);
            let factor = match self.ramp {
                Some(w) => ((dphi.abs() * self.jump_scale - (self.threshold - w)) / w).clamp(0.0, 1.0),
                None => {
                    if open.get(k).copied().unwrap_or(false) {
                        1.0
                    } else {
                        0.0
                    }
                }
            };
            let f_p = if factor > 0.0 {
                let d = factor * self.alpha * 0.5 * (self.d_p[a] + self.d_p[b]);
                let v = -(d / self.vt) * dphi / dx;
                -d * (y[3 * b] - y[3 * a]) / dx + v * self.face_value(y, f, 0, v)
            } else {
                0.0
            };
            (f_p, 0.0, g)
        }
    }

    /// The DAE's right-hand side (mass matrix diag(1, 1, 0) per cell).
    pub fn rhs(&self, y: &[f64], open: &[bool], out: &mut [f64]) {
        let dx = self.dx;
        let (mut fp_l, mut fn_l, mut g_l) = self.face(y, open, 0);
        for i in 0..self.n {
            let (fp_r, fn_r, g_r) = self.face(y, open, i + 1);
            out[3 * i] = (fp_l - fp_r) / dx;
            out[3 * i + 1] = (fn_l - fn_r) / dx;
            out[3 * i + 2] = self.k_poisson * (g_r - g_l) / dx + y[3 * i] - y[3 * i + 1];
            (fp_l, fn_l, g_l) = (fp_r, fn_r, g_r);
        }
    }

    /// The right-hand side the BDF's Newton iteration works with: [`Model::rhs`], with each
    /// electrode cell's electron row replaced, for `electron_rows = "field"`, by itself plus
    /// `mu_i = sigma_i / (k eps_i)` times the cell's Poisson row `g_i` (k = eps0/e):
    ///
    /// `n_i' = (X[i] - X[i+1]) / dx + (p_i - n_i) / tau_i`, `tau_i = k eps_i / sigma_i`,
    ///
    /// with the excess flux `X[f] = F_n[f] - (sigma_i / eps_i) G[f]` of face f, exactly 0 on a
    /// face inside the electrode (both sides carry sigma_i and eps_i), so it is computed only
    /// at the electrode's two ends. A row operation that adds multiples of algebraic rows to
    /// differential ones leaves the mass matrix unchanged (T M = M), so the BDF equations
    /// `M (y - psi) = c f(y)` and `M (y - psi) = c T f(y)` have the same solutions and Newton's
    /// corrections are the same in exact arithmetic; what changes is the rounding: `F_n[i] -
    /// F_n[i+1]` is a difference of two nearly equal fluxes `sigma dphi/dx`, each rounded to
    /// `sigma ulp(phi)/dx`, so the row's floor was `sigma ulp(phi)/dx^2` (1e4x finer grid, 1e4x
    /// higher floor); the new row has no potential inside the electrode.
    pub fn newton_rhs(&self, y: &[f64], open: &[bool], out: &mut [f64]) {
        self.rhs(y, open, out);
        if self.electron_rows != ElectronRows::Field {
            return;
        }
        let dx = self.dx;
        let n = self.n;
        for i in (0..n).filter(|&i| self.region[i].is_electrode() && self.sigma[i] > 0.0) {
            let r = self.region[i];
            let ratio = self.sigma[i] / self.eps[i];
            // The excess flux of a face at the electrode's end (0 on a face inside it).
            let excess = |f: usize| -> f64 {
                let inside = f > 0 && f < n && self.region[f - 1] == r && self.region[f] == r;
                if inside {
                    0.0
                } else {
                    let (_, f_n, g) = self.face(y, open, f);
                    f_n - ratio * g
                }
            };
            let relax = ratio / self.k_poisson * (y[3 * i] - y[3 * i + 1]);
            out[3 * i + 1] = (excess(i) - excess(i + 1)) / dx + relax;
        }
    }

    /// The inventories (per area) whose rates do not depend on the state, as weights on the
    /// unknowns, `I_k = w_k . y`: for each species (p; n = electrons or anions), the cells of
    /// each material, joined across an interface where cations may cross it (for p, an open
    /// or ramped interface). No electron or anion crosses an interface, no cation an end, the
    /// ends' electron currents are given: each such inventory changes at a fixed rate, so
    /// `w_k^T f(y)` is constant and `w_k^T J = 0` for every state, and the Newton matrix
    /// A = M - cJ has `w_k^T A = w_k^T M`: an exact Newton correction x of `A x = b` changes
    /// the inventory by exactly `w_k^T b`. Requires the insulating right end (a reservoir's
    /// fluxes depend on the state) and the electron rows in flux form (the field form adds
    /// Poisson rows); empty there and where `scheme.charge_exact_solve = false`. The net
    /// charge is in their span.
    pub fn invariants(&self, open: &[bool]) -> Vec<Vec<f64>> {
        if !self.charge_exact_solve || self.right != Right::Insulating || self.electron_rows != ElectronRows::Potential {
            return vec![];
        }
        let crossable =
            |f: usize| self.ramp.is_some() || self.interfaces.binary_search(&f).ok().and_then(|k| open.get(k).copied()).unwrap_or(false);
        let mut out = vec![];
        for var in 0..2 {
            let mut start = 0;
            for i in 1..=self.n {
                let end = i == self.n || (self.region[i] != self.region[i - 1] && !(var == 0 && crossable(i)));
                if end {
                    let mut w = vec![0.0; self.len()];
                    for c in start..i {
                        w[3 * c + var] = self.dx;
                    }
                    out.push(w);
                    start = i;
                }
            }
        }
        out
    }

    /// Every face's fluxes and field.
    pub fn faces(&self, y: &[f64], open: &[bool]) -> Faces {
        let mut out = Faces { f_p: vec![], f_n: vec![], g: vec![] };
        for f in 0..=self.n {
            let (a, b, c) = self.face(y, open, f);
            out.f_p.push(a);
            out.f_n.push(b);
            out.g.push(c);
        }
        out
    }

    /// The weight of face f in the Poisson rows: eps_r over the distance between the two
    /// potentials it joins (G[f] = w_f (phi_right - phi_left)); 0 at an insulating end.
    #[inline]
    pub fn poisson_weight(&self, f: usize) -> f64 {
        let n = self.n;
        if f == 0 {
            self.eps_face[0] / (0.5 * self.dx)
        } else if f == n {
            match self.right {
                Right::Insulating => 0.0,
                Right::Reservoir { .. } => self.eps_face[n] / (0.5 * self.dx),
            }
        } else {
            self.eps_face[f] / self.dx
        }
    }

    /// d(Poisson row i)/d(unknown `var` of cell c): the rows are linear, so exact.
    #[inline]
    pub fn poisson_derivative(&self, i: usize, c: usize, var: usize) -> f64 {
        let k = self.k_poisson / self.dx;
        match var {
            0 if c == i => 1.0,
            1 if c == i => -1.0,
            2 if c == i => -k * (self.poisson_weight(i) + self.poisson_weight(i + 1)),
            2 if c == i + 1 => k * self.poisson_weight(i + 1),
            2 if c + 1 == i => k * self.poisson_weight(i),
            _ => 0.0,
        }
    }

    /// Solves the Poisson rows exactly for phi given p and n (Thomas algorithm, O(N)).
    pub fn solve_poisson(&self, y: &mut [f64]) {
        let right = match self.right {
            Right::Reservoir { phi, .. } => phi,
            Right::Insulating => 0.0,
        };
        self.solve_poisson_with(y, self.phi_left, right);
        // Iterative refinement against the Poisson rows as the integrator evaluates them. The
        // Thomas solve alone leaves a residual far above the rows' own rounding at fine grids
        // (the matrix's condition number grows as N^2: at 1e5 cells 6e-13 of the row terms,
        // phi off by 5e-8 V next to the anode interface), which Newton then removes in the
        // first step after every restart, a jump independent of the step size that the error
        // test rejects until the step underflows (the 1e5-cell failure at the first switch).
        let mut rows = vec![0.0; y.len()];
        let mut last = f64::INFINITY;
        for _ in 0..4 {
            let (mut g_l, mut worst) = (self.face(y, &[], 0).2, 0.0f64);
            for i in 0..self.n {
                let g_r = self.face(y, &[], i + 1).2;
                let r = self.k_poisson * (g_r - g_l) / self.dx + y[3 * i] - y[3 * i + 1];
                worst = worst.max(r.abs());
                // The correction d solves M d = -(dx/k) r: the rows are linear in phi.
                rows[3 * i] = r;
                rows[3 * i + 1] = 0.0;
                g_l = g_r;
            }
            if worst == 0.0 || worst >= 0.5 * last {
                break;
            }
            last = worst;
            self.solve_poisson_with(&mut rows, 0.0, 0.0);
            for i in 0..self.n {
                y[3 * i + 2] += rows[3 * i + 2];
            }
        }
    }

    /// phi' from p' and n' (the time derivative of the constraint; the boundary potentials
    /// are constant): `dy` holds p', n' and receives phi'.
    pub fn solve_poisson_derivative(&self, dy: &mut [f64]) {
        self.solve_poisson_with(dy, 0.0, 0.0);
    }

    fn solve_poisson_with(&self, y: &mut [f64], phi_left: f64, phi_right: f64) {
        let n = self.n;
        let dx = self.dx;
        let w = |f: usize| self.poisson_weight(f);
        // Row i: w_i phi_{i-1} - (w_i + w_{i+1}) phi_i + w_{i+1} phi_{i+1} = -(p - n) dx / k.
        let mut c_prime = vec![0.0; n];
        let mut d_prime = vec![0.0; n];
        for i in 0..n {
            let lower = if i > 0 { w(i) } else { 0.0 };
            let upper = if i + 1 < n { w(i + 1) } else { 0.0 };
            let diag = -(w(i) + w(i + 1));
            let mut rhs = -(y[3 * i] - y[3 * i + 1]) * dx / self.k_poisson;
            if i == 0 {
                rhs -= w(0) * phi_left;
            }
            if i + 1 == n {
                rhs -= w(n) * phi_right;
            }
            let denom = diag - lower * if i > 0 { c_prime[i - 1] } else { 0.0 };
            c_prime[i] = upper / denom;
            d_prime[i] = (rhs - lower * if i > 0 { d_prime[i - 1] } else { 0.0 }) / denom;
        }
        let mut phi_next = 0.0;
        for i in (0..n).rev() {
            let phi = d_prime[i] - if i + 1 < n { c_prime[i] * phi_next } else { 0.0 };
            y[3 * i + 2] = phi;
            phi_next = phi;
        }
    }

    /// The largest Poisson-row residual (1/nm^3) and the scale it is measured against: the
    /// largest sum of the magnitudes of a row's terms, (eps0/e)(|G_l| + |G_r|)/dx + |p| + |n|.
    pub fn poisson_residual(&self, y: &[f64], open: &[bool]) -> (f64, f64) {
        let mut out = vec![0.0; self.len()];
        self.rhs(y, open, &mut out);
        let r = (0..self.n).map(|i| out[3 * i + 2].abs()).fold(0.0, f64::max);
        let mut g_l = self.face(y, open, 0).2;
        let mut scale: f64 = 0.0;
        for i in 0..self.n {
            let g_r = self.face(y, open, i + 1).2;
            scale = scale.max(self.k_poisson * (g_l.abs() + g_r.abs()) / self.dx + y[3 * i].abs() + y[3 * i + 1].abs());
            g_l = g_r;
        }
        (r, scale)
    }

    /// The switch functions of the interfaces: the switch's drop ([`Model::switch_drop`]) minus
    /// the level at which the face's switch flips (threshold when closed, threshold -
    /// hysteresis when open).
    pub fn switch_functions(&self, y: &[f64], open: &[bool], out: &mut [f64]) {
        for (k, &f) in self.interfaces.iter().enumerate() {
            out[k] = self.switch_drop(y, f) - if open[k] { self.threshold - self.hysteresis } else { self.threshold };
        }
    }

    pub fn totals(&self, y: &[f64]) -> Totals {
        let dx = self.dx;
        let mut t = Totals::default();
        for i in 0..self.n {
            let (p, c) = (y[3 * i], y[3 * i + 1]);
            t.cations += p * dx;
            if self.region[i].is_electrode() {
                t.electrons += c * dx;
            } else {
                t.anions += c * dx;
            }
            if self.region[i] == Region::Cathode {
                t.cathode_electrons += c * dx;
            }
            t.charge += (p - c) * dx;
            t.charge_abs += (p - c).abs() * dx;
            t.min_p = t.min_p.min(p);
        }
        t
    }

    /// The discrete Gauss law over the whole cell: (eps0/e)(G[0] - G[N]) = Q; returns
    /// (eps0/e)(G[0] - G[N]), Q and the field at x = 0 (V/nm).
    pub fn gauss(&self, y: &[f64], open: &[bool]) -> (f64, f64, f64) {
        let (_, _, g0) = self.face(y, open, 0);
        let (_, _, gn) = self.face(y, open, self.n);
        let q = self.totals(y).charge;
        (self.k_poisson * (g0 - gn), q, g0 / self.eps_face[0])
    }

    /// Cells of the stencil of a residual row's cell: the columns of cells i-2..=i+2.
    pub const STENCIL: usize = 2;
}

/// Inventories per unit area (1/nm^2).
#[derive(Debug, Clone, Copy)]
pub struct Totals {
    pub cations: f64,
    pub electrons: f64,
    pub anions: f64,
    pub cathode_electrons: f64,
    pub charge: f64,
    pub charge_abs: f64,
    pub min_p: f64,
}

impl Default for Totals {
    fn default() -> Self {
        Totals { cations: 0.0, electrons: 0.0, anions: 0.0, cathode_electrons: 0.0, charge: 0.0, charge_abs: 0.0, min_p: f64::INFINITY }
    }
}
