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
        let mut t = Totals { mass: 0.0, momentum: [0.0; D], kinetic: 0.0, internal: 0.0 };
        for p in 0..pts.len() {
            t.mass += pts.mass[p];
            for a in 0..D {
                t.momentum[a] += pts.mass[p] * pts.v[p][a];
                t.kinetic += 0.5 * pts.mass[p] * pts.v[p][a] * pts.v[p][a];
            }
            t.internal += pts.internal_energy[p];
        }
        t
    }

    pub fn energy(&self) -> f64 {
        self.kinetic + self.internal
    }
}
