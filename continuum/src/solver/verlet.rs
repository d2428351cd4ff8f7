//! The Stormer-Verlet step of the battery thesis (B 5.3, Table 5.1 column 2; notes A.7, its
//! garbled layout reconstructed):
//! 1. stencil, m_i, v_i^n, f_i^n and a^n at x^n;
//! 2. half kick v_i^{n+1/2} = v_i^n + dt/2 a_i^n (boundary conditions applied);
//! 3. l_p^n = sum v_i^{n+1/2} (x) grad phi^n;
//! 4. drift x_p^{n+1} = x_p^n + dt sum phi^n v_i^{n+1/2}, and the first half of the velocity
//!    update v_p += dt/2 sum phi^n a_i^n (the FLIP increment of the half kick);
//! 5. the stencil at x^{n+1} and l_p^{n+1} = sum v_i^{n+1/2} (x) grad phi^{n+1};
//! 6. F: F_dot = (l^n F^n + l^{n+1} F^{n+1}) / 2 is implicit but linear: solved,
//!    (I - dt/2 l^{n+1}) F^{n+1} = (I + dt/2 l^n) F^n [derived]; the closure gets the velocity
//!    gradient L with I + dt L = (I - dt/2 l^{n+1})^-1 (I + dt/2 l^n) (so F^{n+1} = (I + dt L) F^n
//!    exactly; rate laws see L = (l^n + l^{n+1})/2 + O(dt));
//! 7. the stress from the closure at F^{n+1};
//! 8. m_i^{n+1} = sum phi^{n+1} m_p [proposed; the table reuses m_i], f^{n+1} (body force at
//!    t^{n+1}) and a^{n+1};
//! 9. v_p^{n+1} = v_p^n + dt/2 (sum phi^n a^n + sum phi^{n+1} a^{n+1}).
//!
//! Velocities and positions both belong to t^n (no stagger), and step 8's forces are the next
//! step's step 1 (not reused here: each step assembles twice). Linear analysis
//! (the stability module): [[1 - r s/2, r (1 - s/4)], [-s, 1 - s/2]] on (v, dt a), det
//! 1 - s (1 - r)/2, stable for s <= 4: c dt / h <= 1 for MPM at any number of points per cell.
//! FLIP only (no PIC/FLIP blend).

use super::*;

impl<const D: usize> Simulation<D> {
    /// One Stormer-Verlet step (see the module notes).
    pub(super) fn verlet_step(&mut self) -> Result<StepReport, SolverError> {
        let step = self.step + 1;
        let dt = self.dt;
        let cause = "time step too large or a domain sheared past its limit (use cpdi1 or ddmp)";
        self.build_stencil(None).map_err(|o| stencil_error(step, &o, cause))?;
        self.correct_gradients(step)?;
        let c = self.wave_speed();
        self.map_velocities(step)?;
        self.nodal_forces();
        self.half_kick(step, c)?;
        self.velocity_gradients();
        self.filter_velocity_gradients(step)?;
        let l_old = self.points.vel_grad.clone();
        // Drift with v^{n+1/2} and the first half of the FLIP increment.
        self.move_points();
        self.build_stencil(None).map_err(|o| stencil_error(step, &o, cause))?;
        self.correct_gradients(step)?;
        self.velocity_gradients();
        self.filter_velocity_gradients(step)?;
        let half = 0.5 * dt;
        self.points.vel_grad.par_iter_mut().zip(l_old.par_iter()).with_min_len(CHUNK).for_each(|(l1, l0)| {
            let lhs = tensor::add_scaled(&tensor::IDENTITY, l1, -half);
            let rhs = tensor::add_scaled(&tensor::IDENTITY, l0, half);
            *l1 = match tensor::inverse(&lhs) {
                Some(inv) => {
                    tensor::add_scaled(&tensor::ZERO, &tensor::add_scaled(&tensor::mul(&inv, &rhs), &tensor::IDENTITY, -1.0), 1.0 / dt)
                }
                None => [[f64::NAN; 3]; 3],
            };
        });
        if let Some(p) = self.points.vel_grad.iter().position(|l| !tensor::is_finite(l)) {
            return Err(SolverError::Diverged {
                step,
                what: format!("particle {p}: I - dt/2 l^(n+1) is singular in the Stormer-Verlet F update"),
                cause: "time step too large for the velocity gradient",
            });
        }
        self.advance_scalar(step)?;
        self.deform_and_stress(step, c)?;
        // Forces at the new positions, body force at t^{n+1}, and the second half kick.
        self.time += dt;
        self.map_velocities(step)?;
        self.nodal_forces();
        self.half_kick(step, c)?;
        let (st, nv, nvl) = (&self.stencil, &self.node_v, &self.node_v_lagrangian);
        self.points.v.par_iter_mut().enumerate().with_min_len(CHUNK).for_each(|(p, v)| {
            let (nodes, weights, _) = st.row(p);
            for (&i, &w) in nodes.iter().zip(weights) {
                for a in 0..D {
                    v[a] += w * (nvl[i][a] - nv[i][a]);
                }
            }
        });
        self.step = step;
        self.integration_point_updates = self.integration_point_updates.saturating_add((self.points.len() * self.sub_points) as u64);
        self.guard(step)?;
        Ok(StepReport { step, time: self.time })
    }

    /// node_v_lagrangian = node_v + dt/2 f / m with the boundary conditions (the solver's
    /// Lagrangian update over half a step).
    fn half_kick(&mut self, step: u64, c: f64) -> Result<(), SolverError> {
        let dt = self.dt;
        self.dt = 0.5 * dt;
        let r = self.lagrangian_update(step, c);
        self.dt = dt;
        r
    }
}
