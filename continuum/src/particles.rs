//! Material points as structure-of-arrays. Points of one body are contiguous, so a closure
//! sees a body as one slice.

use crate::tensor::{IDENTITY, Mat3, ZERO};
use std::ops::Range;

#[derive(Debug, Clone, Default)]
pub struct Particles<const D: usize> {
    /// Initial position (m).
    pub x0: Vec<[f64; D]>,
    /// Current position (m).
    pub x: Vec<[f64; D]>,
    /// Velocity (m/s).
    pub v: Vec<[f64; D]>,
    /// Mass (kg; kg/m^2 in 1D, kg/m in 2D).
    pub mass: Vec<f64>,
    /// Volume in the reference (unstrained) configuration.
    pub volume0: Vec<f64>,
    /// Current volume (m^3; m in 1D, m^2 in 2D).
    pub volume: Vec<f64>,
    /// Half-lengths of the point's domain along each axis at the start (m), for GIMP-like schemes.
    pub half_length: Vec<[f64; D]>,
    /// Deformation gradient from the reference configuration.
    pub def_grad: Vec<Mat3>,
    /// Velocity gradient of the last step, L_ij = dv_i/dx_j (1/s).
    pub vel_grad: Vec<Mat3>,
    /// Cauchy stress from the closure (Pa, tension positive), without artificial viscosity.
    pub stress: Vec<Mat3>,
    /// Artificial viscous pressure of the last step, -tr(q)/3 (Pa, >= 0 in compression).
    pub visc_pressure: Vec<f64>,
    /// Artificial viscous stress q of the last step (Pa, tension positive; added to `stress`
    /// in the internal force). The linear form is -q I, the tensor form (7.8) is anisotropic.
    pub visc_stress: Vec<Mat3>,
    /// Reference half-vectors of the point's domain: column `a` is the domain's half-extent
    /// along axis `a` in the reference configuration, so the current half-vectors are
    /// `F * domain0` (CPDI1 parallelograms, sub-point placement).
    pub domain0: Vec<Mat3>,
    /// Tracked domain corners (CPDI in 1D, CPDI2), `2^D` per point: corner `k` of point `p`
    /// is `corners[p * 2^D + k]` and lies on the side `+` of axis `a` when bit `a` of `k` is
    /// set. Moved with the grid velocity every step (6.28).
    pub corners: Vec<[f64; D]>,
    /// Work done on the point by stresses since the start (J, per unit cross-section in 1D).
    pub internal_energy: Vec<f64>,
    /// Index of the body each point belongs to.
    pub body: Vec<u32>,
    /// Scalar field carried by the points (normalised concentration c = c_Li / c_max, or a
    /// temperature); empty unless the scene has one ([`Particles::with_fields`]).
    pub scalar: Vec<f64>,
    /// Its rate over the last step (1/s); empty with `scalar`.
    pub scalar_rate: Vec<f64>,
    /// Equivalent plastic strain; empty unless a law of the scene is plastic.
    pub plastic_strain: Vec<f64>,
}

impl<const D: usize> Particles<D> {
    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Appends one point at rest state `F = def_grad` with the given reference volume.
    #[allow(clippy::too_many_arguments)]
    pub fn push(&mut self, body: u32, x: [f64; D], v: [f64; D], mass: f64, volume0: f64, half_length: [f64; D], def_grad: Mat3) {
        let j = crate::tensor::det(&def_grad);
        // Reference half-vectors: F0^-1 diag(half_length) (the given half-lengths are current).
        let mut cur = ZERO;
        for a in 0..D {
            cur[a][a] = half_length[a];
        }
        let inv = crate::tensor::inverse(&def_grad).unwrap_or(IDENTITY);
        self.domain0.push(crate::tensor::mul(&inv, &cur));
        for k in 0..(1usize << D) {
            self.corners.push(std::array::from_fn(|a| if k >> a & 1 == 1 { x[a] + half_length[a] } else { x[a] - half_length[a] }));
        }
        self.x0.push(x);
        self.x.push(x);
        self.v.push(v);
        self.mass.push(mass);
        self.volume0.push(volume0);
        self.volume.push(volume0 * j);
        self.half_length.push(half_length);
        self.def_grad.push(def_grad);
        self.vel_grad.push(ZERO);
        self.stress.push(ZERO);
        self.visc_pressure.push(0.0);
        self.visc_stress.push(ZERO);
        self.internal_energy.push(0.0);
        self.body.push(body);
    }

    /// Allocates the optional per-point fields (zero) once every point is pushed: the scalar
    /// field and its rate, and the plastic strain. Scenes without them allocate nothing.
    pub fn with_fields(&mut self, scalar: bool, plastic: bool) {
        let n = self.len();
        if scalar {
            self.scalar.resize(n, 0.0);
            self.scalar_rate.resize(n, 0.0);
        }
        if plastic {
            self.plastic_strain.resize(n, 0.0);
        }
    }

    /// Corners per point (`2^D`).
    pub const CORNERS: usize = 1 << D;

    /// Current half-vector of the point's domain along axis `a` (column `a` of `F * domain0`).
    pub fn half_vector(&self, p: usize, a: usize) -> [f64; D] {
        let (f, r) = (&self.def_grad[p], &self.domain0[p]);
        std::array::from_fn(|i| (0..3).map(|k| f[i][k] * r[k][a]).sum())
    }

    pub fn density(&self, p: usize) -> f64 {
        self.mass[p] / self.volume[p]
    }

    /// Mean pressure -tr(sigma)/3 (Pa), without artificial viscosity.
    pub fn pressure(&self, p: usize) -> f64 {
        -crate::tensor::trace(&self.stress[p]) / 3.0
    }

    /// The contiguous range of points of each body, in body order.
    pub fn body_ranges(&self) -> Vec<Range<usize>> {
        let mut ranges: Vec<Range<usize>> = Vec::new();
        for (p, &b) in self.body.iter().enumerate() {
            match ranges.get_mut(b as usize) {
                Some(r) => r.end = p + 1,
                None => {
                    while ranges.len() < b as usize {
                        ranges.push(p..p);
                    }
                    ranges.push(p..p + 1);
                }
            }
        }
        ranges
    }
}

impl<const D: usize> Particles<D> {
    /// The closure batch of the points in `range` (one body) for continuum step `step`.
    pub fn batch(&mut self, step: u64, range: Range<usize>) -> crate::closure::ClosureBatch<'_> {
        crate::closure::ClosureBatch {
            step,
            first: range.start,
            vel_grad: &self.vel_grad[range.clone()],
            def_grad: &self.def_grad[range.clone()],
            mass: &self.mass[range.clone()],
            volume: &self.volume[range.clone()],
            scalar_rate: if self.scalar_rate.is_empty() { &[] } else { &self.scalar_rate[range.clone()] },
            plastic_strain: if self.plastic_strain.is_empty() { &mut [] } else { &mut self.plastic_strain[range.clone()] },
            visc_stress: if self.visc_stress.is_empty() { &[] } else { &self.visc_stress[range.clone()] },
            stress: &mut self.stress[range],
        }
    }

    /// Identity deformation gradient (for callers building points by hand).
    pub fn identity() -> Mat3 {
        IDENTITY
    }
}
