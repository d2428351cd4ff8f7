//! IMPM, Gong's improved MPM (Ch. 5, eqs. 5.3-5.4, 5.15-5.25; notes A.2), in 1D: the grid
//! half of the step. The rest (Lagrangian nodal update with the leapfrog's half first step,
//! strain rate, deformation and stress, particle update) is the solver's own, with the hat
//! functions at x_p^s as the stencil.
//!
//! 1. Nodal velocity v_i = sum_p Phi_p(x_i) v_p: MLS with the linear basis and the cubic
//!    B-spline (G 5.1); this maps velocity, not momentum. Only the nodes of cells holding
//!    points get one (the others move nothing; beyond a free surface they may see one point).
//! 2. Cell centres x_c: rho_c = sum_p Q_p(x_c) rho_p, sigma_c and b_c likewise, MLS with the
//!    linear basis and the quadratic B-spline (G 5.2).
//! 3. One-point quadrature per cell: m_i = sum_c rho_c N_i(x_c) Omega_c (5.14),
//!    f_i = -sum_c dN_i/dx(x_c) sigma_c Omega_c + sum_c N_i(x_c) rho_c b_c Omega_c (5.9)-(5.10),
//!    with N_i(x_c) = 1/2 and dN_i/dx = -+1/h (errata of the 1D code: +-1/h, not +-h, and the
//!    factor Omega_c in m_i and f_ext).
//!
//! Partly filled cells and free surfaces (the thesis leaves them open; [proposed] in the
//! notes): Omega_c is the length of the cell covered by the union of the points' current
//! domains [x_p - V_p / 2, x_p + V_p / 2] (h for a full cell, which gives Gong's scheme
//! exactly; less at a free surface; 0 in an empty cell, which is skipped). A surface cell is
//! therefore integrated over its filled part at its centre's reconstructed density and stress
//! (one point, not moved to the filled part's centre): the traction-free condition holds only to
//! O(h) there. A centre with a filled part whose quadratic support is degenerate (fewer than two
//! distinct points) stops the run with the MLS error naming the cell centre. IMPM does not
//! conserve momentum exactly: the velocity map is not mass-weighted and the quadrature mass
//! differs from sum_p M_p N_i(x_p) (notes A.2).

use super::*;
use crate::mls::{Basis, Empty, Mls, ShapeTable, SingularMoment, Weight};

impl<const D: usize> Simulation<D> {
    /// Steps 1-3 of IMPM: fills `node_v`, `node_mass` and `node_force` (1D).
    pub(super) fn impm_grid(&mut self, step: u64) -> Result<(), SolverError> {
        assert_eq!(D, 1, "impm is implemented in 1D");
        let singular = |e: SingularMoment| SolverError::Diverged {
            step,
            what: e.to_string(),
            cause: "too few distinct particles near that node or cell centre (use more particles per cell)",
        };
        let velocity = self.mls_velocity_table(step)?;
        let (grid, pts) = (&self.grid, &self.points);
        let (h, x0, cells) = (grid.h[0], grid.origin[0], grid.cells[0]);
        // Omega_c: the covered length of each cell.
        let mut spans: Vec<(f64, f64)> =
            (0..pts.len()).map(|p| (pts.x[p][0] - 0.5 * pts.volume[p], pts.x[p][0] + 0.5 * pts.volume[p])).collect();
        spans.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut omega = vec![0.0; cells];
        let mut add = |lo: f64, hi: f64| {
            let first = (((lo - x0) / h).floor().max(0.0) as usize).min(cells.saturating_sub(1));
            for c in first..cells {
                let (a, b) = (x0 + c as f64 * h, x0 + (c + 1) as f64 * h);
                if a >= hi {
                    break;
                }
                omega[c] += (hi.min(b) - lo.max(a)).max(0.0);
            }
        };
        let mut current: Option<(f64, f64)> = None;
        for &(lo, hi) in &spans {
            current = match current {
                Some((a, b)) if lo <= b => Some((a, b.max(hi))),
                Some((a, b)) => {
                    add(a, b);
                    Some((lo, hi))
                }
                None => Some((lo, hi)),
            };
        }
        if let Some((a, b)) = current {
            add(a, b);
        }
        let filled: Vec<usize> = (0..cells).filter(|&c| omega[c] > 1e-12 * h).collect();
        let centres: Vec<[f64; D]> = filled.iter().map(|&c| std::array::from_fn(|_| x0 + (c as f64 + 0.5) * h)).collect();
        let q = Mls::new(Basis::Linear, Weight::QuadraticBSpline, grid.h)
            .table(&centres, &pts.x, Empty::Refuse, "cell centre", |k| filled[k])
            .map_err(singular)?;
        let rho: Vec<f64> = (0..pts.len()).map(|p| pts.density(p)).collect();
        let sigma: Vec<f64> = (0..pts.len()).map(|p| pts.stress[p][0][0] + pts.visc_stress[p][0][0]).collect();
        let body: Option<Vec<f64>> = self.body_force.as_ref().map(|f| (0..pts.len()).map(|p| f(&pts.x0[p], self.time)[0]).collect());
        self.node_mass.iter_mut().for_each(|m| *m = 0.0);
        self.node_force.iter_mut().for_each(|f| *f = [0.0; D]);
        for (k, &c) in filled.iter().enumerate() {
            let w = omega[c].min(h);
            let (rho_c, sigma_c) = (q.apply(k, &rho), q.apply(k, &sigma));
            let b_c = body.as_ref().map_or(0.0, |b| q.apply(k, b));
            for (i, grad) in [(c, -1.0 / h), (c + 1, 1.0 / h)] {
                self.node_mass[i] += 0.5 * rho_c * w;
                self.node_force[i][0] += -grad * sigma_c * w + 0.5 * rho_c * b_c * w;
            }
        }
        self.apply_velocity_table(&velocity);
        Ok(())
    }

    /// The MLS velocity map of IMPM and `cpdi-improved` (Gong 5.3 step 1, 6.6): the nodes of
    /// every cell holding a point (the stencil that moves them; a node farther out may see a
    /// single point and gets none), linear basis, cubic B-spline, in D dimensions. Returns the
    /// table with the active nodes' linear indices.
    pub(super) fn mls_velocity_table(&self, step: u64) -> Result<(Vec<usize>, ShapeTable), SolverError> {
        let (grid, pts) = (&self.grid, &self.points);
        if let Some(a) = (0..D).find(|&a| grid.periodic(a)) {
            return Err(SolverError::Diverged {
                step,
                what: format!("axis {a} is periodic"),
                cause: "the MLS velocity map (impm, cpdi-improved) does not wrap around a periodic axis in this build",
            });
        }
        let mut needed = vec![false; grid.node_count()];
        for x in &pts.x {
            let cell: [usize; D] = std::array::from_fn(|a| {
                (((x[a] - grid.origin[a]) / grid.h[a]).floor().max(0.0) as usize).min(grid.cells[a].saturating_sub(1))
            });
            for corner in 0..(1usize << D) {
                needed[grid.linear(std::array::from_fn(|a| cell[a] + (corner >> a & 1)))] = true;
            }
        }
        let active: Vec<usize> = (0..grid.node_count()).filter(|&i| needed[i]).collect();
        let nodes: Vec<[f64; D]> = active.iter().map(|&i| grid.node_position(grid.unlinear(i))).collect();
        let table = Mls::new(Basis::Linear, Weight::CubicBSpline, grid.h)
            .table(&nodes, &pts.x, Empty::Refuse, "node", |k| active[k])
            .map_err(|e: SingularMoment| SolverError::Diverged {
                step,
                what: e.to_string(),
                cause: "too few distinct particles near that node (use more particles per cell)",
            })?;
        Ok((active, table))
    }

    /// node_v = sum_p Phi_p(x_i) v_p at the active nodes (zero elsewhere), then the velocity
    /// boundary conditions.
    pub(super) fn apply_velocity_table(&mut self, velocity: &(Vec<usize>, ShapeTable)) {
        let (active, table) = velocity;
        let pts = &self.points;
        self.node_v.iter_mut().for_each(|v| *v = [0.0; D]);
        let comps: Vec<Vec<f64>> = (0..D).map(|a| pts.v.iter().map(|v| v[a]).collect()).collect();
        for (k, &i) in active.iter().enumerate() {
            self.node_v[i] = std::array::from_fn(|a| table.apply(k, &comps[a]));
        }
        // A PIC share starts from this map (the same projection below, and its impulse).
        self.set_pic_base();
        let mass = std::mem::take(&mut self.node_mass);
        self.grid.apply_boundaries(&mass, &mut self.node_v);
        self.node_mass = mass;
    }

    /// Steps 3-4 of the cycle: the lumped mass and mapped velocity; `cpdi-improved` then
    /// replaces the velocity by the MLS map (Gong 6.6), keeping the CPDI mass.
    pub(super) fn map_velocities(&mut self, step: u64) -> Result<(), SolverError> {
        self.map_to_grid();
        if self.scheme == SchemeKind::CpdiImproved {
            let table = self.mls_velocity_table(step)?;
            self.apply_velocity_table(&table);
        }
        Ok(())
    }
}

/// The CPDI whose mass and forces `cpdi-improved` keeps: the 1D CPDI, or cpdi2 in 2D/3D.
pub(super) fn improved_cpdi_base<const D: usize>() -> SchemeKind {
    if D == 1 { SchemeKind::Cpdi } else { SchemeKind::Cpdi2 }
}
