//! LAMMPS `metal` unit constants (the values LAMMPS 2021 uses in `update.cpp`, so that
//! energies, temperatures and pressures agree with LAMMPS to round-off).
//!
//! Lengths in A, time in ps, velocities in A/ps, masses in amu, energies in eV, temperature
//! in K. Stress leaves the engine in GPa, tension positive.

/// amu * A^2 / ps^2 to eV.
pub const MVV2E: f64 = 1.0364269e-4;
/// eV / A / amu to A / ps^2 (force over mass to acceleration).
pub const FTM2V: f64 = 1.0 / 1.0364269e-4;
/// Boltzmann constant in eV / K.
pub const BOLTZ: f64 = 8.617343e-5;
/// eV / A^3 to bar (LAMMPS `nktv2p` for metal units).
pub const NKTV2P: f64 = 1.6021765e6;
/// eV / A^3 to GPa.
pub const EV_PER_A3_TO_GPA: f64 = NKTV2P * 1e-4;
