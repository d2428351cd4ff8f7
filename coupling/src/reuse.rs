//! MD-call avoidance of an md body (`[bodies.X.material] reuse`).
//!
//! - `off`: every box is stepped every continuum step.
//! - `exact`: results bitwise those of `off`. Boxes whose states are bitwise identical (a
//!   content hash, point ids left out) and that are sent bitwise identical work are stepped
//!   once for all of them by the pool ([`md_worker::reuse`]): every box of a uniform region
//!   before a wave reaches it is one box. A class that splits gives its members the state of
//!   before the call through the pool's snapshot and restore.
//! - `{ tolerance = GPa, max_interval = steps }`: on top of `exact`, a box is not stepped while
//!   the change of its stress predicted since its last MD call stays below `tolerance` (GPa),
//!   for at most `max_interval` continuum steps in a row. See [`Skip`] for what the prediction
//!   is and what skipping does to the box.

use serde::{Deserialize, Serialize};

/// Default `max_interval` of the tolerance mode (continuum steps).
pub const DEFAULT_MAX_INTERVAL: u64 = 20;

/// How an md body avoids MD calls.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(try_from = "RawReuse", into = "RawReuse")]
pub enum Reuse {
    #[default]
    Off,
    Exact,
    Tolerance {
        /// GPa: a box is skipped while its predicted stress change since its last MD call is
        /// below this (largest Voigt component).
        tolerance_gpa: f64,
        /// Continuum steps a box may be skipped in a row.
        max_interval: u64,
    },
}

impl Reuse {
    /// Whether the pool shares the computation of identical boxes (every mode but `off`).
    pub fn exact_sharing(&self) -> bool {
        !matches!(self, Reuse::Off)
    }

    /// As written in a scene (`off`, `exact`, `tolerance 0.05 GPa, max 20 steps`).
    pub fn describe(&self) -> String {
        match self {
            Reuse::Off => "off".into(),
            Reuse::Exact => "exact".into(),
            Reuse::Tolerance { tolerance_gpa, max_interval } => format!("tolerance {tolerance_gpa} GPa, max_interval {max_interval}"),
        }
    }
}

/// The scene's spelling: a string or a table.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(untagged)]
enum RawReuse {
    Name(String),
    Table(RawTolerance),
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTolerance {
    tolerance: f64,
    #[serde(default = "default_max_interval")]
    max_interval: u64,
}

fn default_max_interval() -> u64 {
    DEFAULT_MAX_INTERVAL
}

impl TryFrom<RawReuse> for Reuse {
    type Error = String;
    fn try_from(r: RawReuse) -> Result<Self, String> {
        match r {
            RawReuse::Name(n) if n == "off" => Ok(Reuse::Off),
            RawReuse::Name(n) if n == "exact" => Ok(Reuse::Exact),
            RawReuse::Name(n) => Err(format!(
                "reuse = {n:?}: allowed \"off\", \"exact\" or {{ tolerance = GPa, max_interval = continuum steps (default {DEFAULT_MAX_INTERVAL}) }}"
            )),
            RawReuse::Table(t) => Ok(Reuse::Tolerance { tolerance_gpa: t.tolerance, max_interval: t.max_interval }),
        }
    }
}

impl From<Reuse> for RawReuse {
    fn from(r: Reuse) -> Self {
        match r {
            Reuse::Off => RawReuse::Name("off".into()),
            Reuse::Exact => RawReuse::Name("exact".into()),
            Reuse::Tolerance { tolerance_gpa, max_interval } => RawReuse::Table(RawTolerance { tolerance: tolerance_gpa, max_interval }),
        }
    }
}

/// What the tolerance mode keeps of a box between its MD calls.
///
/// The approximation, exactly: while a box is skipped, the point's stress is the box's last
/// MD stress plus the predicted change, `sigma_last + ds (de . e) / (de . de)`, where `e` is
/// the strain the point accumulated since the box's last MD call (the sum of sym(L) dt over
/// the continuum steps), and (`ds`, `de`) are the stress change and strain of the box's last
/// MD call that strained it by at least the tolerance's worth (`c11 |de| >= tolerance`): the
/// box's own measured secant tangent along its last direction of straining. The strain
/// orthogonal to `de` is not predicted; `c11` times it counts in full against the tolerance.
/// A box is skipped while that predicted change plus the unpredicted part stays below the
/// tolerance and it was skipped fewer than `max_interval` steps in a row.
///
/// The box itself does not move while skipped: its clock, temperature and atoms stay at its
/// last MD call, and the MD steps of the skipped continuum steps are never done (that is the
/// saving). At its next call the box catches up the point's deformation, not its time: one
/// continuum step's MD steps at the sum of the velocity gradients of the skipped steps and the
/// current one, so its shape is the point's again (to second order in the rate's variation),
/// while its own clock stays behind the continuum's by the skipped time for good, and it sees
/// the skipped deformation `n + 1` times faster than the point did. The work the continuum did
/// with the predicted stresses while the box was skipped joins the energy balance of that call
/// (energy consistency). What is lost: the box's thermal evolution over the skipped time and
/// the rate history inside the interval. At 0 K, where a crystal's stress follows its
/// deformation, that loss is small; at a temperature, keep the interval short.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Skip {
    /// Continuum steps skipped since the box's last MD call.
    pub skipped: u64,
    /// Sum of the skipped steps' velocity gradients (1/ps).
    pub l_sum: [[f64; 3]; 3],
    /// Strain since the last MD call (xx, yy, zz, xy, xz, yz; tensor shear components).
    pub strain: [f64; 6],
    /// Stress given to the point at the previous continuum step (GPa, Voigt).
    pub reported_gpa: [f64; 6],
    /// The box's measured secant: stress change and strain of its last informative MD call.
    pub secant: Option<([f64; 6], [f64; 6])>,
    /// Continuum work on the box over the skipped steps (eV), with the predicted stresses.
    pub work_ev: f64,
    /// Viscous heat of the skipped steps (eV), added at the catch-up.
    #[serde(default)]
    pub heat_ev: f64,
}

/// Strain increment (Voigt order, tensor shear) of a velocity gradient `l` (1/ps) over `t` ps.
pub fn strain_increment(l: &[[f64; 3]; 3], t: f64) -> [f64; 6] {
    let d = |i: usize, j: usize| 0.5 * (l[i][j] + l[j][i]) * t;
    [d(0, 0), d(1, 1), d(2, 2), d(0, 1), d(0, 2), d(1, 2)]
}

fn dot(a: &[f64; 6], b: &[f64; 6]) -> f64 {
    // Shear components count twice (the tensor's xy and yx).
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + 2.0 * (a[3] * b[3] + a[4] * b[4] + a[5] * b[5])
}

fn max_abs(a: &[f64; 6]) -> f64 {
    a.iter().fold(0.0, |m, v| m.max(v.abs()))
}

impl Skip {
    /// The predicted stress change for a total strain `e` since the last MD call, and the
    /// estimate of how far the prediction may be from the box's (GPa): the predicted change
    /// plus `c11` times the strain the secant does not cover.
    pub fn predict(&self, e: &[f64; 6], c11_gpa: f64) -> ([f64; 6], f64) {
        let (change, rest) = match &self.secant {
            Some((ds, de)) if dot(de, de) > 0.0 => {
                let a = dot(de, e) / dot(de, de);
                (std::array::from_fn(|c| a * ds[c]), std::array::from_fn(|c| e[c] - a * de[c]))
            }
            _ => ([0.0; 6], *e),
        };
        let bound = max_abs(&change) + c11_gpa * max_abs(&rest);
        (change, bound)
    }

    /// After an MD call that strained the box by `e` and changed its stress by `ds`: keeps the
    /// secant when the strain is large enough to resolve a stress change of `tolerance_gpa`
    /// and its modulus along `e` is plausible (between 1/20 and 20 times `c11`).
    pub fn measured(&mut self, ds: [f64; 6], e: [f64; 6], c11_gpa: f64, tolerance_gpa: f64) {
        let ee = dot(&e, &e);
        if !(ee > 0.0) || c11_gpa * max_abs(&e) < tolerance_gpa {
            return;
        }
        let modulus = dot(&ds, &e) / ee;
        self.secant = if modulus.is_finite() && modulus > c11_gpa / 20.0 && modulus < 20.0 * c11_gpa { Some((ds, e)) } else { None };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_secant_predicts_along_its_direction_and_bounds_the_rest() {
        let mut s = Skip::default();
        // No secant yet: nothing predicted, the whole strain counts at c11.
        let (ch, bound) = s.predict(&[1e-3, 0.0, 0.0, 0.0, 0.0, 0.0], 170.0);
        assert_eq!(ch, [0.0; 6]);
        assert!((bound - 0.17).abs() < 1e-12);
        // Uniaxial: C11 = 170, C12 = 120 GPa.
        s.measured([0.17, 0.12, 0.12, 0.0, 0.0, 0.0], [1e-3, 0.0, 0.0, 0.0, 0.0, 0.0], 170.0, 0.05);
        let (ch, bound) = s.predict(&[-5e-4, 0.0, 0.0, 0.0, 0.0, 0.0], 170.0);
        assert!((ch[0] + 0.085).abs() < 1e-12 && (ch[1] + 0.06).abs() < 1e-12);
        assert!((bound - 0.085).abs() < 1e-12);
        // A strain too small to resolve the tolerance keeps the old secant.
        s.measured([1.0, 0.0, 0.0, 0.0, 0.0, 0.0], [1e-6, 0.0, 0.0, 0.0, 0.0, 0.0], 170.0, 0.05);
        assert_eq!(s.secant.map(|x| x.0[0]), Some(0.17));
        // An implausible modulus drops it.
        s.measured([-0.17, 0.0, 0.0, 0.0, 0.0, 0.0], [1e-3, 0.0, 0.0, 0.0, 0.0, 0.0], 170.0, 0.05);
        assert!(s.secant.is_none());
    }

    #[test]
    fn scene_spellings_round_trip() {
        #[derive(Serialize, Deserialize)]
        struct M {
            reuse: Reuse,
        }
        let m = |t: &str| serde_json::from_str::<M>(t).map(|m| m.reuse);
        assert_eq!(m(r#"{"reuse":"off"}"#).unwrap(), Reuse::Off);
        assert_eq!(m(r#"{"reuse":"exact"}"#).unwrap(), Reuse::Exact);
        assert_eq!(
            m(r#"{"reuse":{"tolerance":0.1}}"#).unwrap(),
            Reuse::Tolerance { tolerance_gpa: 0.1, max_interval: DEFAULT_MAX_INTERVAL }
        );
        assert!(m(r#"{"reuse":"sometimes"}"#).unwrap_err().to_string().contains("allowed \"off\", \"exact\""));
        let t = Reuse::Tolerance { tolerance_gpa: 0.05, max_interval: 7 };
        assert_eq!(serde_json::to_string(&M { reuse: t }).unwrap(), r#"{"reuse":{"tolerance":0.05,"max_interval":7}}"#);
    }
}
