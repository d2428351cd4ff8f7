//! Total-Lagrangian MPM as a scheme of the solver (`scheme.method = "tlmpm"`; battery thesis
//! 6.1, wave2 notes C.1; the 1D library form with its derivations is [`crate::tlmpm`]).
//!
//! The stencil (hat weights S0_ip and their reference gradients G0_ip) is built once at the
//! points' reference positions X_p, with the tiles of every scatter sorted by X_p; the nodal
//! masses m_i = sum_p S0_ip m_p are therefore the same every step. A step (velocities at half
//! steps: the validator requires `integrator = "leapfrog"`, whose first step kicks by dt / 2):
//! (`Simulation::step` runs this for the scheme `Tlmpm` whatever `integrator` says, and sets
//! it to `Leapfrog`, which the velocity time of the outputs then reads.)
//! 1. v_i = sum_p S0_ip m_p v_p / m_i with the boundary conditions (the solver's map, small-mass
//!    treatment included);
//! 2. f_i = -sum_p V0_p P_p G0_ip + sum_p S0_ip m_p b_p(X_p, t), with the first Piola-Kirchhoff
//!    stress P = J (sigma + q) F^-T of the closure's Cauchy stress and the viscous stress;
//! 3. v*_i = v_i + dt f_i / m_i with the boundary conditions (the solver's Lagrangian update:
//!    its acceleration guard and wall impulse);
//! 4. x_p += dt sum S0 v*_i, v_p = beta (v_p + sum S0 (v*_i - v_i)) + (1 - beta) sum S0 v*_i
//!    (6.33; the solver's point update);
//! 5. v'_i = sum_p S0_ip m_p v_p / m_i (6.34) and F_p += dt sum_i v'_i (x) G0_ip (6.36-6.37):
//!    passed to the closures as L_p = (sum_i v'_i (x) G0_ip) F_p^-1, so the solver's
//!    F <- (I + dt L) F gives that F to round-off and the hypoelastic laws see the rate they
//!    expect.
//!
//! No point ever changes its stencil: there is no cell-crossing error, and the scheme converges
//! at second order on the manufactured solution at G = 0.1 (tests/tlmpm.rs). Its linear bound
//! (hats, 2 points per cell, FLIP) is c dt / h <= sqrt 3, not 1: the F update sees the
//! re-mapped velocity, whose symbol r = 1 - (3/4) sin^2(theta / 2) softens the sawtooth
//! (the `stability` module derives it for any points per cell and blend).
//!
//! Everything the step carries lives on the points (the nodal velocity is re-mapped from them
//! every step), so a checkpoint of the points resumes bit for bit.
//!
//! **Moving mesh** (`Simulation::moving_mesh`, `scheme.tlmpm_form = "moving-mesh"`; 6.25-6.28,
//! 6.35; the library's `Form::MovingMesh`): the nodal velocity is carried instead of re-mapped.
//! Step 1 maps v_i from the points on the first step only (afterwards v_i is the carried
//! `mesh_velocity`), step 5 takes v'_i = v*_i (no re-map), and with FLIP (the validator asks
//! for flip_fraction 1) step 4 is v_p += sum S0 (v*_i - v_i): the library's v_p += dt sum S a,
//! x_p += dt sum S v_i, F = I + sum u_i (x) G0 (accumulated as F += dt sum v_i (x) G0). The
//! leapfrog then acts on the nodal dofs with the hats' stiffness: bound c dt / h <= 1 at any
//! number of points per cell (`stability::moving_mesh_bound`). Checkpoints carry v_i.

use super::{SolverError, StepReport, row_span};
use crate::par;
use crate::shape::{self, SchemeKind, StencilPart};
use crate::tensor::{self, Mat3};
use crate::{Simulation, particles::Particles};
use rayon::prelude::*;

impl<const D: usize> Simulation<D> {
    /// One TLMPM step (see the module notes).
    pub(super) fn tlmpm_step(&mut self) -> Result<StepReport, SolverError> {
        let step = self.step + 1;
        let dt = self.dt;
        // TLMPM is a leapfrog scheme whatever integrator was set (the scene validator asks for
        // "leapfrog"): the map, the Lagrangian update and the point update read it.
        self.integrator = super::TimeIntegrator::Leapfrog;
        if self.stencil.parts.is_empty() {
            self.reference_stencil().map_err(|o| super::stencil_error(step, &o, "the reference stencil is built at X_p"))?;
        }
        let c = self.wave_speed();
        // The nodal masses (the same every step) and v_i mapped from the points; the moving
        // mesh carries its own v_i after its first step.
        self.map_to_grid();
        if self.moving_mesh && self.mesh_velocity.len() == self.node_v.len() {
            self.node_v.clone_from(&self.mesh_velocity);
        }
        self.piola_forces();
        self.lagrangian_update(step, c)?;
        self.move_points();
        if self.moving_mesh {
            // (6.25-6.28): the updated nodal velocity is carried and drives F (u_i += dt v_i,
            // F = I + sum u_i (x) G0_ip, as F += dt sum v_i (x) G0_ip).
            self.node_v.clone_from(&self.node_v_lagrangian);
            self.mesh_velocity.clone_from(&self.node_v);
        } else {
            // (6.34): the nodal velocity re-mapped from the updated points drives F.
            self.map_to_grid();
        }
        self.reference_velocity_gradients();
        self.advance_scalar(step)?;
        self.deform_and_stress(step, c)?;
        self.time += dt;
        self.step = step;
        self.integration_point_updates = self.integration_point_updates.saturating_add(self.points.len() as u64);
        self.guard(step)?;
        Ok(StepReport { step, time: self.time })
    }

    /// The hat stencil at X_p and the tiles sorted by X_p (once; again after a resume, where
    /// it is rebuilt from the same X_p to the same bits).
    fn reference_stencil(&mut self) -> Result<(), shape::OutsideGrid> {
        let n = self.points.len();
        let mut at = Particles::<D>::default();
        at.x.clone_from(&self.points.x0);
        let (grid, x0) = (&self.grid, &self.points.x0);
        self.tiles.assign(par::slab_tile_count(grid), n, |p| par::slab_tile(grid, &x0[p]));
        let ranges = par::chunk_ranges(n);
        self.stencil.parts.clear();
        self.stencil.parts.resize_with(ranges.len(), StencilPart::default);
        let results: Vec<Result<(), shape::OutsideGrid>> = self
            .stencil
            .parts
            .par_iter_mut()
            .zip(ranges.into_par_iter())
            .map(|(part, r)| {
                part.clear(r.start);
                for p in r {
                    shape::gimp_row(SchemeKind::Mpm, grid, &at, p, part)?;
                    part.end_point();
                }
                Ok(())
            })
            .collect();
        results.into_iter().collect::<Result<(), _>>().inspect_err(|_| self.stencil.parts.clear())
    }

    /// f_i = -sum_p V0_p P_p . G0_ip + sum_p S0_ip m_p b_p, P = J (sigma + q) F^-T.
    fn piola_forces(&mut self) {
        let (st, pts, body, t) = (&self.stencil, &self.points, &self.body_force, self.time);
        self.scatter.run_tiled(
            &self.tiles,
            self.grid.node_count(),
            D,
            &mut self.flat,
            |p| row_span(st, p),
            |tile, w| {
                for &p in tile {
                    let p_k = piola(&pts.def_grad[p], &tensor::add_scaled(&pts.stress[p], &pts.visc_stress[p], 1.0));
                    let v0 = pts.volume0[p];
                    let b = body.as_ref().map(|f| f(&pts.x0[p], t));
                    let (nodes, weights, grads) = st.row(p);
                    for ((&i, g), &sw) in nodes.iter().zip(grads).zip(weights) {
                        let slot = w.slot(i);
                        if let Some(b) = b {
                            for a in 0..D {
                                slot[a] += sw * pts.mass[p] * b[a];
                            }
                        }
                        for a in 0..D {
                            let mut f = 0.0;
                            for k in 0..D {
                                f += p_k[a][k] * g[k];
                            }
                            slot[a] -= v0 * f;
                        }
                    }
                }
            },
        );
        let flat = &self.flat;
        self.node_force.par_iter_mut().enumerate().for_each(|(i, f)| *f = std::array::from_fn(|a| flat[i * D + a]));
        // Light nodes (7.5)-(7.6) as the current-configuration step treats them: the mapped
        // velocity already took their neighbours' average, the force goes with it.
        let floor = self.empty_floor();
        let eps = self.small_mass;
        if eps > 0.0 && self.node_mass.iter().any(|&m| m > floor && m <= eps) {
            self.node_force = super::distribute(&self.grid, &self.node_mass, &self.node_force, |m| m > floor && m <= eps);
        }
    }

    /// L_p = (sum_i v'_i (x) G0_ip) F_p^-1 with the re-mapped nodal velocity v'.
    fn reference_velocity_gradients(&mut self) {
        let (st, v, f) = (&self.stencil, &self.node_v, &self.points.def_grad);
        par::for_chunks_mut(&mut self.points.vel_grad, 1, |r, out| {
            for (k, p) in r.enumerate() {
                let (nodes, _, grads) = st.row(p);
                let mut fdot: Mat3 = tensor::ZERO;
                for (&i, g) in nodes.iter().zip(grads) {
                    for a in 0..D {
                        for b in 0..D {
                            fdot[a][b] += v[i][a] * g[b];
                        }
                    }
                }
                // A singular F stops the run in the guard of `deform_and_stress` (J <= 0) or
                // the closure; the identity keeps this pass total.
                let inv = tensor::inverse(&f[p]).unwrap_or(tensor::IDENTITY);
                out[k] = tensor::mul(&fdot, &inv);
            }
        });
    }
}

/// The first Piola-Kirchhoff stress P = J sigma F^-T. F is invertible here: the step that
/// made it stopped the run at J <= 0.
fn piola(f: &Mat3, sigma: &Mat3) -> Mat3 {
    let j = tensor::det(f);
    match tensor::inverse(f) {
        Some(inv) => tensor::add_scaled(&tensor::ZERO, &tensor::mul(sigma, &tensor::transpose(&inv)), j),
        None => tensor::ZERO,
    }
}
