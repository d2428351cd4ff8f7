//! Conserved quantities of the point set.

use crate::particles::Particles;

/// Mass, momentum, and energy (kinetic plus stress work) of all points.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Totals<const D: usize> {
    pub mass: f64,
    #[serde(skip)]
    pub momentum: [f64; D],
    pub kinetic: f64,
    pub internal: f64,
}

impl<const D: usize> Default for Totals<D> {
    fn default() -> Self {
        Totals { mass: 0.0, momentum: [0.0; D], kinetic: 0.0, internal: 0.0 }
    }
}

impl<const D: usize> Totals<D> {
    pub fn of(pts: &Particles<D>) -> Self {
        let mut t = Totals::default();
        for p in 0..pts.len() {
            t.add_point(pts, p);
        }
        t
    }

    /// Adds point `p` (in the order [`Totals::of`] adds each point's terms).
    pub fn add_point(&mut self, pts: &Particles<D>, p: usize) {
        self.mass += pts.mass[p];
        for a in 0..D {
            self.momentum[a] += pts.mass[p] * pts.v[p][a];
            self.kinetic += 0.5 * pts.mass[p] * pts.v[p][a] * pts.v[p][a];
        }
        self.internal += pts.internal_energy[p];
    }

    /// Adds `o` field by field.
    pub fn add(&mut self, o: &Totals<D>) {
        self.mass += o.mass;
        for a in 0..D {
            self.momentum[a] += o.momentum[a];
        }
        self.kinetic += o.kinetic;
        self.internal += o.internal;
    }

    pub fn energy(&self) -> f64 {
        self.kinetic + self.internal
    }
}

/// Point `p`'s term of the momentum scale, the sum of m |v| over the points (the scale a run's
/// momentum drift is measured against).
pub fn momentum_magnitude<const D: usize>(pts: &Particles<D>, p: usize) -> f64 {
    pts.mass[p] * pts.v[p].iter().map(|v| v * v).sum::<f64>().sqrt()
}
