//! The continuum side of mscale: material points moving over a fixed background grid,
//! integrated by the explicit cycle of Dhakal's thesis Ch. 3.1 (lumped mass, nodal velocity
//! difference mapped back to the points, positions moved with the average nodal velocity).
//!
//! Main design decision: every scheme (MPM, GIMP, CPDI, DDMP, ...) is reduced to one data
//! structure, a [`shape::Stencil`]: for every point the list of nodes it touches with the
//! shape-function value and its (possibly modified) gradient. The step itself
//! ([`solver::Simulation::step`]) only ever talks to stencils, so the schemes differ in one
//! place and 1D, 2D and 3D share one code path through the const generic `D`.
//! Material behaviour enters through the batched [`closure::Closure`] trait, which is where
//! the MD coupling (crate `mscale-coupling`) plugs in. Units are SI throughout (in 1D, mass and volume are per unit
//! cross-section; in 2D per unit thickness).

pub mod closure;
pub mod ddmp;
pub mod diagnostics;
pub mod diffusion;
pub mod exact;
pub mod grid;
pub mod kinematics;
pub mod mls;
#[cfg(feature = "mpi")]
pub mod mpi;
pub mod par;
pub mod particles;
pub mod shape;
pub mod silicon;
pub mod solver;
pub mod stability;
pub mod tensor;
pub mod tlmpm;

pub use closure::{Closure, ClosureBatch, ClosureError};
pub use grid::{Face, Grid};
pub use particles::Particles;
pub use shape::SchemeKind;
pub use solver::{Simulation, SolverError, StepReport};
