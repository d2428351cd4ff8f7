//! Reference-configuration MPM in 1D (battery thesis 6.1, wave2 notes C.1): total-Lagrangian
//! MPM (TLMPM, with the PIC/FLIP blend of (6.33)) and the moving-mesh form, with the first
//! Piola-Kirchhoff stress. Shape functions (hats), their reference gradients and the nodal
//! masses are computed once, at the points' reference positions X_p; no point ever changes
//! cell, so there is no cell-crossing error.
//!
//! Per step, with a_i = f_i / m_i, f_i = -sum_p P_p G0_ip V0_p + sum_p S_ip m_p b_p (6.22,
//! 6.23 with its S_ip):
//! - moving mesh (6.25-6.28, 6.35): v_i += dt a_i, u_i += dt v_i, v_p += dt sum S a,
//!   x_p += dt sum S v_i, F_p = 1 + sum u_i G0_ip;
//! - TLMPM (6.29-6.37): v_i = sum S m_p v_p / m_i (6.34 with its S_ip), v*_i = v_i + dt a_i,
//!   x_p += dt sum S v*_i, v_p = (1 - beta) sum S v*_i + beta (v_p + dt sum S a_i) (6.33),
//!   v_i' = sum S m_p v_p / m_i, F_p += dt sum v_i' G0_ip (6.36-6.37).
//!
//! The first step kicks the velocities by dt / 2 (the leapfrog start), so velocities live at
//! half steps and both forms are second order in time; positions and stresses are at t^n.
//!
//! **Dispersion** (derived; P = E (F - 1), hats, 2 points per cell at 1/4 and 3/4 of the cell,
//! k = c dt / h, theta = kappa h): the moving mesh obeys u^{n+1} - 2 u^n + u^{n-1} = dt^2 K u
//! with K the 3-point Laplacian c^2 / h^2 (6.55), so sin(w dt / 2) = k sin(theta / 2) exactly
//! and the bound is k <= 1 (stable at k = 1 on a fixed-end bar: theta = pi is not one of its
//! modes). TLMPM with beta = 1 keeps the point velocities in the span of the hats, but its
//! F update uses the re-mapped nodal velocity: u^{n+1} - 2 u^n + u^{n-1} = dt^2 R K u with
//! R = S^T M S / m_L, whose symbol for these points is r = 5/8 + 3/8 cos theta
//! = 1 - (3/4) sin^2(theta / 2). Hence sin(w dt / 2) = k sin(theta / 2) sqrt(r), and the bound
//! is k^2 max_s s (1 - 3 s / 4) <= 1 with s = sin^2(theta / 2): max 1/3 at s = 2/3, k <= sqrt 3.
//! ([`dispersion`] gives both; `tests/tlmpm.rs` checks them on the solver to round-off.)

/// Which reference-configuration form.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Form {
    /// Nodal displacements and velocities carried (6.25-6.28, 6.35).
    MovingMesh,
    /// Total-Lagrangian MPM with the PIC/FLIP blend beta of (6.33) (1: FLIP, 0: PIC).
    Total { flip: f64 },
}

/// A 1D first Piola-Kirchhoff law P(F).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Law1d {
    /// P = E (F - 1).
    Linear { modulus: f64 },
    /// The compressible neo-Hookean law of [`crate::closure::NeoHookean`] under uniaxial
    /// strain: sigma = (lambda ln F + mu (F^2 - 1)) / F, and P = J sigma F^-T = sigma in 1D.
    NeoHookean { lambda: f64, mu: f64 },
}

impl Law1d {
    pub fn piola(&self, f: f64) -> f64 {
        match *self {
            Law1d::Linear { modulus } => modulus * (f - 1.0),
            Law1d::NeoHookean { lambda, mu } => (lambda * f.ln() + mu * (f * f - 1.0)) / f,
        }
    }
}

/// A point whose deformation gradient left (0, inf) or became non-finite.
#[derive(Debug, Clone, PartialEq)]
pub struct Inverted {
    pub step: u64,
    pub point: usize,
    pub def_grad: f64,
}

impl std::fmt::Display for Inverted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "step {}: point {} has F = {:e} (inverted or non-finite)", self.step, self.point, self.def_grad)
    }
}

/// Body force per unit mass b(X, t).
pub type BodyForce = Box<dyn Fn(f64, f64) -> f64 + Send + Sync>;

/// A bar [0, length] of `cells` cells with `ppc` evenly spaced points per cell.
pub struct Bar {
    pub form: Form,
    pub law: Law1d,
    pub h: f64,
    pub cells: usize,
    /// Fixed (u = v = 0) at the (min, max) end.
    pub fixed: (bool, bool),
    pub dt: f64,
    pub time: f64,
    pub steps: u64,
    /// Reference positions X_p, current positions x_p, velocities, F, P, masses, V0.
    pub x0: Vec<f64>,
    pub x: Vec<f64>,
    pub v: Vec<f64>,
    pub def_grad: Vec<f64>,
    pub piola: Vec<f64>,
    pub mass: Vec<f64>,
    pub volume0: Vec<f64>,
    /// Nodal masses m_i = sum_p S_ip m_p (once).
    pub node_mass: Vec<f64>,
    /// Nodal displacement u_i (carried by the moving mesh; the accumulated dt v_i' of TLMPM,
    /// for which F_p = 1 + sum u_i G0_ip as well, (6.38)).
    pub node_u: Vec<f64>,
    /// Nodal velocity (moving mesh: carried; TLMPM: the last re-map v_i').
    pub node_v: Vec<f64>,
    pub body_force: Option<BodyForce>,
    /// Per point: its cell (left node), the two hat values and reference gradients (once).
    cell: Vec<usize>,
    weight: Vec<[f64; 2]>,
    grad: Vec<[f64; 2]>,
}

impl Bar {
    /// A bar at rest, F = 1, density `rho0`.
    pub fn new(length: f64, cells: usize, ppc: usize, rho0: f64, law: Law1d, form: Form, dt: f64) -> Self {
        let h = length / cells as f64;
        let n = cells * ppc;
        let v0 = h / ppc as f64;
        let x0: Vec<f64> = (0..n).map(|k| (k as f64 + 0.5) * v0).collect();
        let cell: Vec<usize> = (0..n).map(|k| k / ppc).collect();
        let weight: Vec<[f64; 2]> = x0
            .iter()
            .zip(&cell)
            .map(|(x, &c)| {
                let xi = x / h - c as f64;
                [1.0 - xi, xi]
            })
            .collect();
        let grad = vec![[-1.0 / h, 1.0 / h]; n];
        let mass = vec![rho0 * v0; n];
        let mut node_mass = vec![0.0; cells + 1];
        for p in 0..n {
            for k in 0..2 {
                node_mass[cell[p] + k] += weight[p][k] * mass[p];
            }
        }
        Bar {
            form,
            law,
            h,
            cells,
            fixed: (true, true),
            dt,
            time: 0.0,
            steps: 0,
            x: x0.clone(),
            x0,
            v: vec![0.0; n],
            def_grad: vec![1.0; n],
            piola: vec![0.0; n],
            mass,
            volume0: vec![v0; n],
            node_mass,
            node_u: vec![0.0; cells + 1],
            node_v: vec![0.0; cells + 1],
            body_force: None,
            cell,
            weight,
            grad,
        }
    }

    /// Sets the nodal displacement u_i = u(X_i) and the points' x and F from it.
    pub fn set_displacement(&mut self, u: impl Fn(f64) -> f64) {
        for (i, ui) in self.node_u.iter_mut().enumerate() {
            *ui = u(i as f64 * self.h);
        }
        for p in 0..self.x0.len() {
            let c = self.cell[p];
            let (w, g) = (self.weight[p], self.grad[p]);
            self.x[p] = self.x0[p] + w[0] * self.node_u[c] + w[1] * self.node_u[c + 1];
            self.def_grad[p] = 1.0 + g[0] * self.node_u[c] + g[1] * self.node_u[c + 1];
            self.piola[p] = self.law.piola(self.def_grad[p]);
        }
    }

    /// Sets the points' velocities v(X_p) and the nodal velocities from them (6.34).
    pub fn set_velocity(&mut self, v: impl Fn(f64) -> f64) {
        for p in 0..self.x0.len() {
            self.v[p] = v(self.x0[p]);
        }
        self.node_v = self.map_velocities();
    }

    /// sum_p S_ip m_p v_p / m_i, zero on fixed ends.
    fn map_velocities(&self) -> Vec<f64> {
        let mut mv = vec![0.0; self.cells + 1];
        for p in 0..self.x0.len() {
            for k in 0..2 {
                mv[self.cell[p] + k] += self.weight[p][k] * self.mass[p] * self.v[p];
            }
        }
        for (i, m) in mv.iter_mut().enumerate() {
            *m /= self.node_mass[i];
        }
        self.fix(&mut mv);
        mv
    }

    fn fix(&self, nodal: &mut [f64]) {
        if self.fixed.0 {
            nodal[0] = 0.0;
        }
        if self.fixed.1 {
            nodal[self.cells] = 0.0;
        }
    }

    /// Nodal accelerations a_i = f_i / m_i at the current state and time.
    fn accelerations(&self) -> Vec<f64> {
        let mut f = vec![0.0; self.cells + 1];
        for p in 0..self.x0.len() {
            let b = self.body_force.as_ref().map_or(0.0, |b| b(self.x0[p], self.time));
            for k in 0..2 {
                f[self.cell[p] + k] += -self.piola[p] * self.grad[p][k] * self.volume0[p] + self.weight[p][k] * self.mass[p] * b;
            }
        }
        for (i, fi) in f.iter_mut().enumerate() {
            *fi /= self.node_mass[i];
        }
        self.fix(&mut f);
        f
    }

    /// One step of `dt` (the first kicks the velocities by dt / 2).
    pub fn step(&mut self) -> Result<(), Inverted> {
        let dt = self.dt;
        let kick = if self.steps == 0 { 0.5 * dt } else { dt };
        let a = self.accelerations();
        let n = self.x0.len();
        let interp = |field: &[f64], p: usize, cell: &[usize], w: &[[f64; 2]]| w[p][0] * field[cell[p]] + w[p][1] * field[cell[p] + 1];
        match self.form {
            Form::MovingMesh => {
                for i in 0..=self.cells {
                    self.node_v[i] += kick * a[i];
                    self.node_u[i] += dt * self.node_v[i];
                }
                for p in 0..n {
                    self.v[p] += kick * interp(&a, p, &self.cell, &self.weight);
                    self.x[p] += dt * interp(&self.node_v, p, &self.cell, &self.weight);
                    let c = self.cell[p];
                    self.def_grad[p] = 1.0 + self.grad[p][0] * self.node_u[c] + self.grad[p][1] * self.node_u[c + 1];
                }
            }
            Form::Total { flip } => {
                let vstar: Vec<f64> = (0..=self.cells).map(|i| self.node_v[i] + kick * a[i]).collect();
                for p in 0..n {
                    let vs = interp(&vstar, p, &self.cell, &self.weight);
                    self.x[p] += dt * vs;
                    let flipped = self.v[p] + kick * interp(&a, p, &self.cell, &self.weight);
                    self.v[p] = if flip == 1.0 { flipped } else { (1.0 - flip) * vs + flip * flipped };
                }
                self.node_v = self.map_velocities();
                for i in 0..=self.cells {
                    self.node_u[i] += dt * self.node_v[i];
                }
                for p in 0..n {
                    let c = self.cell[p];
                    self.def_grad[p] += dt * (self.grad[p][0] * self.node_v[c] + self.grad[p][1] * self.node_v[c + 1]);
                }
            }
        }
        self.steps += 1;
        self.time += dt;
        for p in 0..n {
            let f = self.def_grad[p];
            if !(f.is_finite() && f > 0.0) {
                return Err(Inverted { step: self.steps, point: p, def_grad: f });
            }
            self.piola[p] = self.law.piola(f);
        }
        Ok(())
    }
}

/// cos(w dt) of the mode theta = kappa h at k = c dt / h on the linear law, hats and 2 points
/// per cell at 1/4 and 3/4 (derived in the module notes): 1 - 2 k^2 sin^2(theta/2) for the
/// moving mesh, 1 - 2 k^2 s (1 - 3 s / 4) with s = sin^2(theta/2) for TLMPM at beta = 1.
/// A value below -1 is an unstable mode.
pub fn dispersion(form: Form, k: f64, theta: f64) -> f64 {
    let s = (0.5 * theta).sin().powi(2);
    match form {
        Form::MovingMesh => 1.0 - 2.0 * k * k * s,
        Form::Total { .. } => 1.0 - 2.0 * k * k * s * (1.0 - 0.75 * s),
    }
}
