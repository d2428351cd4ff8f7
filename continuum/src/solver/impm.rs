//! IMPM, Gong's improved MPM (Ch. 5, eqs. 5.3-5.4, 5.15-5.25; notes A.2), in 1D, 2D and 3D
//! (Gong runs it in 1D and on the 2D manufactured solution, Figs 5.7-5.8): the grid half of the
//! step. The rest (Lagrangian nodal update with the leapfrog's half first step,
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
//!    factor Omega_c in m_i and f_ext); in D dimensions the multilinear hats at the element
//!    centre: N_i = 1/2^D, dN_i/dx_a = +-1/(h_a 2^(D-1)), and sigma_c is the full tensor.
//!
//! Partly filled cells and free surfaces (the thesis leaves them open; [proposed] in the
//! notes): Omega_c is the length of the cell covered by the union of the points' current
//! domains [x_p - V_p / 2, x_p + V_p / 2] (h for a full cell, which gives Gong's scheme
//! exactly; less at a free surface; 0 in an empty cell, which is skipped). In 2D and 3D the
//! union has no cheap exact form: Omega_c is the cell's volume where the cell and its face
//! neighbours hold points, else the points' volume in the cell, at most the cell's (notes A.2's
//! proposal; see `filled_volumes`). One-point quadrature on multilinear cells has the
//! hourglass modes of any one-point element; Gong's 2D test (diagonal F) does not excite
//! them, and nothing here damps them (measured on the 2D manufactured solution only). A surface cell is
//! therefore integrated over its filled part at its centre's reconstructed density and stress
//! (one point, not moved to the filled part's centre): the traction-free condition holds only to
//! O(h) there. A centre with a filled part whose quadratic support is degenerate (fewer than two
//! distinct points) stops the run with the MLS error naming the cell centre. IMPM does not
//! conserve momentum exactly: the velocity map is not mass-weighted and the quadrature mass
//! differs from sum_p M_p N_i(x_p) (notes A.2).

use super::*;
use crate::mls::{Basis, Empty, Mls, ShapeTable, SingularMoment, Weight};

impl<const D: usize> Simulation<D> {
    /// Steps 1-3 of IMPM: fills `node_v`, `node_mass` and `node_force` (1D, 2D, 3D).
    pub(super) fn impm_grid(&mut self, step: u64) -> Result<(), SolverError> {
        let singular = |e: SingularMoment| SolverError::Diverged {
            step,
            what: e.to_string(),
            cause: "too few distinct particles near that node or cell centre (use more particles per cell)",
        };
        let velocity = self.mls_velocity_table(step)?;
        let (grid, pts) = (&self.grid, &self.points);
        let omega = if D == 1 { covered_lengths(grid, pts) } else { filled_volumes(grid, pts) };
        let cell_count: usize = grid.cells.iter().product();
        let filled: Vec<usize> = (0..cell_count).filter(|&c| omega[c] > 1e-12 * grid.cell_volume()).collect();
        let centres: Vec<[f64; D]> = filled
            .iter()
            .map(|&c| {
                let idx = cell_index(grid, c);
                std::array::from_fn(|a| grid.origin[a] + (idx[a] as f64 + 0.5) * grid.h[a])
            })
            .collect();
        let q = Mls::new(Basis::Linear, Weight::QuadraticBSpline, grid.h)
            .table(&centres, &pts.x, Empty::Refuse, "cell centre", |k| filled[k])
            .map_err(singular)?;
        let rho: Vec<f64> = (0..pts.len()).map(|p| pts.density(p)).collect();
        // The stress components the forces need (sigma_ab, a, b < D), artificial viscosity included.
        let sigma: Vec<Vec<f64>> = (0..D * D)
            .map(|ab| (0..pts.len()).map(|p| pts.stress[p][ab / D][ab % D] + pts.visc_stress[p][ab / D][ab % D]).collect())
            .collect();
        let body: Option<Vec<Vec<f64>>> =
            self.body_force.as_ref().map(|f| (0..D).map(|a| (0..pts.len()).map(|p| f(&pts.x0[p], self.time)[a]).collect()).collect());
        self.node_mass.iter_mut().for_each(|m| *m = 0.0);
        self.node_force.iter_mut().for_each(|f| *f = [0.0; D]);
        // At a cell centre every node of the cell has N_i = 1 / 2^D and dN_i/dx_a = +-1 / (h_a 2^(D-1)).
        let n_c = 1.0 / (1usize << D) as f64;
        for (k, &c) in filled.iter().enumerate() {
            let w = omega[c].min(grid.cell_volume());
            let rho_c = q.apply(k, &rho);
            let sigma_c: Vec<f64> = sigma.iter().map(|s| q.apply(k, s)).collect();
            let b_c: [f64; D] = std::array::from_fn(|a| body.as_ref().map_or(0.0, |b| q.apply(k, &b[a])));
            let idx = cell_index(grid, c);
            for corner in 0..(1usize << D) {
                let i = grid.linear(std::array::from_fn(|a| idx[a] + (corner >> a & 1)));
                let grad: [f64; D] =
                    std::array::from_fn(|a| if corner >> a & 1 == 1 { 2.0 * n_c / grid.h[a] } else { -2.0 * n_c / grid.h[a] });
                self.node_mass[i] += n_c * rho_c * w;
                for a in 0..D {
                    let div: f64 = (0..D).map(|b| sigma_c[a * D + b] * grad[b]).sum();
                    self.node_force[i][a] += -div * w + n_c * rho_c * b_c[a] * w;
                }
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
        if self.scheme.is_cpdi_improved() {
            let table = self.mls_velocity_table(step)?;
            self.apply_velocity_table(&table);
        }
        Ok(())
    }
}

/// The CPDI whose mass and forces an improved CPDI keeps: `cpdi-improved` the 1D CPDI, or
/// cpdi2 in 2D/3D; `cpdi1-improved` cpdi1.
pub(super) fn improved_cpdi_base<const D: usize>(scheme: SchemeKind) -> SchemeKind {
    match scheme {
        SchemeKind::Cpdi1Improved => SchemeKind::Cpdi1,
        _ if D == 1 => SchemeKind::Cpdi,
        _ => SchemeKind::Cpdi2,
    }
}

/// The multi-index of cell `c` (axis 0 fastest, as the nodes).
fn cell_index<const D: usize>(grid: &Grid<D>, mut c: usize) -> [usize; D] {
    std::array::from_fn(|a| {
        let i = c % grid.cells[a];
        c /= grid.cells[a];
        i
    })
}

/// The cell of a point (clamped to the grid), as a linear cell index.
fn cell_of<const D: usize>(grid: &Grid<D>, x: &[f64; D]) -> usize {
    let mut c = 0;
    for a in (0..D).rev() {
        let i = (((x[a] - grid.origin[a]) / grid.h[a]).floor().max(0.0) as usize).min(grid.cells[a].saturating_sub(1));
        c = c * grid.cells[a] + i;
    }
    c
}

/// Omega_c in 1D: the length of each cell covered by the union of the points' current domains
/// [x_p - V_p / 2, x_p + V_p / 2] (h for a full cell, less at a free surface, 0 if empty).
fn covered_lengths<const D: usize>(grid: &Grid<D>, pts: &Particles<D>) -> Vec<f64> {
    let (h, x0, cells) = (grid.h[0], grid.origin[0], grid.cells[0]);
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
    omega
}

/// Omega_c in 2D and 3D (the union of the points' domains has no cheap exact form there): the
/// whole cell where the cell and each face neighbour inside the grid hold points (the interior
/// of a body); elsewhere, at a free surface, the points' volume in the cell, at most the cell's
/// (notes A.2 [proposed]). A body that starts aligned with the grid fills its surface cells
/// exactly, so both rules give the cell's volume there at the start.
fn filled_volumes<const D: usize>(grid: &Grid<D>, pts: &Particles<D>) -> Vec<f64> {
    let count: usize = grid.cells.iter().product();
    let (mut held, mut volume) = (vec![false; count], vec![0.0; count]);
    for p in 0..pts.len() {
        let c = cell_of(grid, &pts.x[p]);
        held[c] = true;
        volume[c] += pts.volume[p];
    }
    let full = grid.cell_volume();
    (0..count)
        .map(|c| {
            if !held[c] {
                return 0.0;
            }
            let idx = cell_index(grid, c);
            let mut stride = 1;
            let mut interior = true;
            for a in 0..D {
                if idx[a] > 0 && !held[c - stride] || idx[a] + 1 < grid.cells[a] && !held[c + stride] {
                    interior = false;
                }
                stride *= grid.cells[a];
            }
            if interior { full } else { volume[c].min(full) }
        })
        .collect()
}
