//! Physical constants in the units of the cell model (nm, s, V, e).

/// Elementary charge (C), Boltzmann's constant (J/K) and the vacuum permittivity
/// (C/(V nm)), as in the thesis (8.6).
pub const E_CHARGE: f64 = 1.602e-19;
pub const K_B: f64 = 1.38e-23;
pub const EPS0: f64 = 8.854e-21;

/// 1 cm^2/s in nm^2/s.
pub const CM2_PER_S: f64 = 1e14;
