//! Lattice builders and deterministic random velocities.

use crate::error::MdError;
use crate::units::{BOLTZ, MVV2E};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha20Rng;
use serde::{Deserialize, Serialize};

/// Cubic lattices, conventional cell, orientation [100] [010] [001].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LatticeKind {
    /// Face-centred cubic, 4 atoms per cell.
    Fcc,
    /// Body-centred cubic, 2 atoms per cell.
    Bcc,
    /// Simple cubic, 1 atom per cell.
    Sc,
}

impl std::str::FromStr for LatticeKind {
    type Err = MdError;
    fn from_str(s: &str) -> Result<Self, MdError> {
        match s {
            "fcc" => Ok(LatticeKind::Fcc),
            "bcc" => Ok(LatticeKind::Bcc),
            "sc" => Ok(LatticeKind::Sc),
            _ => Err(MdError::invalid("lattice", format!("{s:?}; expected fcc, bcc or sc"))),
        }
    }
}

impl LatticeKind {
    fn basis(self) -> &'static [[f64; 3]] {
        match self {
            LatticeKind::Fcc => &[[0.0, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [0.0, 0.5, 0.5]],
            LatticeKind::Bcc => &[[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]],
            LatticeKind::Sc => &[[0.0, 0.0, 0.0]],
        }
    }
}

/// Crystal directions along the box's x, y and z axes (integer Miller indices), as in LAMMPS
/// `lattice ... orient x .. orient y .. orient z ..`: mutually orthogonal and right-handed.
/// The box repeats along axis k every `a0 |o_k|` (LAMMPS's lattice spacing for that axis), so
/// one "cell" of an oriented box holds `basis * |o_x| |o_y| |o_z|` atoms.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Orientation(pub [[i32; 3]; 3]);

impl Default for Orientation {
    fn default() -> Self {
        Orientation::CUBE
    }
}

impl std::str::FromStr for Orientation {
    type Err = MdError;
    /// `X/Y/Z` with three integers each, e.g. `1,1,0/-1,1,0/0,0,1`; checked as [`Orientation::validate`].
    fn from_str(s: &str) -> Result<Self, MdError> {
        let bad = || {
            MdError::invalid(
                "orientation",
                format!("{s:?}; expected three directions X/Y/Z of three integers each, e.g. 1,1,0/-1,1,0/0,0,1"),
            )
        };
        let rows: Vec<Vec<i32>> = s
            .split('/')
            .map(|r| r.split(',').map(|c| c.trim().parse::<i32>()).collect::<Result<_, _>>())
            .collect::<Result<_, _>>()
            .map_err(|_| bad())?;
        if rows.len() != 3 || rows.iter().any(|r| r.len() != 3) {
            return Err(bad());
        }
        let o = Orientation(std::array::from_fn(|k| [rows[k][0], rows[k][1], rows[k][2]]));
        o.validate()?;
        Ok(o)
    }
}

impl Orientation {
    /// x = [100], y = [010], z = [001].
    pub const CUBE: Orientation = Orientation([[1, 0, 0], [0, 1, 0], [0, 0, 1]]);

    fn dot(a: &[i32; 3], b: &[i32; 3]) -> i64 {
        (0..3).map(|k| a[k] as i64 * b[k] as i64).sum()
    }

    /// Checks the directions: non-zero, mutually orthogonal, right-handed, components within
    /// +/-12 (larger indices make boxes of tens of thousands of atoms per cell).
    pub fn validate(&self) -> Result<(), MdError> {
        let o = &self.0;
        let bad = |msg: String| Err(MdError::invalid("lattice orientation", format!("{o:?}: {msg}")));
        if o.iter().flatten().any(|c| c.abs() > 12) {
            return bad("components must lie in -12..=12".into());
        }
        if let Some(k) = (0..3).find(|&k| Self::dot(&o[k], &o[k]) == 0) {
            return bad(format!("the {} direction is zero", ["x", "y", "z"][k]));
        }
        for (a, b) in [(0, 1), (0, 2), (1, 2)] {
            if Self::dot(&o[a], &o[b]) != 0 {
                return bad(format!("the {} and {} directions are not orthogonal", ["x", "y", "z"][a], ["x", "y", "z"][b]));
            }
        }
        let cross = [
            o[0][1] as i64 * o[1][2] as i64 - o[0][2] as i64 * o[1][1] as i64,
            o[0][2] as i64 * o[1][0] as i64 - o[0][0] as i64 * o[1][2] as i64,
            o[0][0] as i64 * o[1][1] as i64 - o[0][1] as i64 * o[1][0] as i64,
        ];
        if (0..3).map(|k| cross[k] * o[2][k] as i64).sum::<i64>() < 0 {
            return bad("left-handed: z must be along x cross y (flip the sign of one direction)".into());
        }
        Ok(())
    }

    /// Repeat length of axis `k` in units of a0: |o_k|.
    pub fn period(&self, k: usize) -> f64 {
        (Self::dot(&self.0[k], &self.0[k]) as f64).sqrt()
    }

    /// Conventional cells in one oriented cell: |o_x| |o_y| |o_z| (an integer for orthogonal
    /// integer directions: the determinant).
    pub fn cube_cells(&self) -> u64 {
        let o = &self.0;
        let det = o[0][0] as i64 * (o[1][1] as i64 * o[2][2] as i64 - o[1][2] as i64 * o[2][1] as i64)
            - o[0][1] as i64 * (o[1][0] as i64 * o[2][2] as i64 - o[1][2] as i64 * o[2][0] as i64)
            + o[0][2] as i64 * (o[1][0] as i64 * o[2][1] as i64 - o[1][1] as i64 * o[2][0] as i64);
        det.unsigned_abs()
    }
}

impl LatticeKind {
    /// Atoms per oriented cell.
    pub fn atoms_per_cell(self, orient: &Orientation) -> u64 {
        self.basis().len() as u64 * orient.cube_cells()
    }
}

/// Positions of `cells` conventional cells of lattice constant `a0` (A), box [0, cells * a0).
pub fn build_lattice(kind: LatticeKind, a0: f64, cells: [usize; 3]) -> (Vec<[f64; 3]>, [f64; 3]) {
    let mut x = Vec::new();
    for i in 0..cells[0] {
        for j in 0..cells[1] {
            for k in 0..cells[2] {
                for b in kind.basis() {
                    x.push([(i as f64 + b[0]) * a0, (j as f64 + b[1]) * a0, (k as f64 + b[2]) * a0]);
                }
            }
        }
    }
    (x, [cells[0] as f64 * a0, cells[1] as f64 * a0, cells[2] as f64 * a0])
}

/// Positions of `cells` oriented cells (box [0, cells_k a0 |o_k|) along axis k). The cube
/// orientation gives exactly [`build_lattice`]. Which lattice sites fall in the half-open box
/// is decided in integer arithmetic (doubled crystal coordinates), so no site is lost or
/// doubled on a face by round-off.
pub fn build_oriented(kind: LatticeKind, a0: f64, cells: [usize; 3], orient: &Orientation) -> Result<(Vec<[f64; 3]>, [f64; 3]), MdError> {
    orient.validate()?;
    if *orient == Orientation::CUBE {
        return Ok(build_lattice(kind, a0, cells));
    }
    let o = &orient.0;
    let norm2: [i64; 3] = std::array::from_fn(|k| Orientation::dot(&o[k], &o[k]));
    let lengths: [f64; 3] = std::array::from_fn(|k| cells[k] as f64 * a0 * orient.period(k));
    // Box corner k along axis k, in crystal coordinates (units of a0): cells_k o_k.
    let mut lo = [i64::MAX; 3];
    let mut hi = [i64::MIN; 3];
    for corner in 0..8 {
        for d in 0..3 {
            let c: i64 = (0..3).filter(|k| corner >> k & 1 == 1).map(|k| cells[k] as i64 * o[k][d] as i64).sum();
            lo[d] = lo[d].min(c);
            hi[d] = hi[d].max(c);
        }
    }
    let basis2: Vec<[i64; 3]> = kind.basis().iter().map(|b| std::array::from_fn(|d| (2.0 * b[d]) as i64)).collect();
    let mut x = Vec::new();
    for i in lo[0] - 1..=hi[0] {
        for j in lo[1] - 1..=hi[1] {
            for k in lo[2] - 1..=hi[2] {
                for b in &basis2 {
                    // Doubled crystal coordinates of the site and its projections on the axes.
                    let c2 = [2 * i + b[0], 2 * j + b[1], 2 * k + b[2]];
                    let s2: [i64; 3] = std::array::from_fn(|a| (0..3).map(|d| o[a][d] as i64 * c2[d]).sum());
                    // Inside when 0 <= o_a . c < cells_a |o_a|^2 for every axis a.
                    if (0..3).all(|a| s2[a] >= 0 && s2[a] < 2 * cells[a] as i64 * norm2[a]) {
                        x.push(std::array::from_fn(|a| 0.5 * s2[a] as f64 * a0 / orient.period(a)));
                    }
                }
            }
        }
    }
    let expected = kind.atoms_per_cell(orient) * cells.iter().map(|&c| c as u64).product::<u64>();
    if x.len() as u64 != expected {
        return Err(MdError::invalid(
            "lattice orientation",
            format!("{o:?} gave {} atoms for {cells:?} cells, expected {expected} (internal error)", x.len()),
        ));
    }
    Ok((x, lengths))
}

/// The generator for a (seed, point id, purpose, step) tuple: independent streams per box.
pub fn rng_for(seed: u64, point: u64, purpose: u64, step: u64) -> ChaCha20Rng {
    let mut key = [0u8; 32];
    key[..8].copy_from_slice(&seed.to_le_bytes());
    key[8..16].copy_from_slice(&point.to_le_bytes());
    key[16..24].copy_from_slice(&purpose.to_le_bytes());
    key[24..].copy_from_slice(&step.to_le_bytes());
    ChaCha20Rng::from_seed(key)
}

/// A standard normal deviate (Box-Muller, so the stream is ours and stable).
pub fn normal(rng: &mut ChaCha20Rng) -> f64 {
    let u1: f64 = 1.0 - rng.r#gen::<f64>(); // (0, 1]
    let u2: f64 = rng.r#gen::<f64>();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// Maxwell velocities (A/ps) at exactly temperature `t` (K), zero total momentum.
pub fn maxwell_velocities(rng: &mut ChaCha20Rng, masses: &[f64], t: f64) -> Vec<[f64; 3]> {
    let n = masses.len();
    let mut v: Vec<[f64; 3]> = masses
        .iter()
        .map(|m| {
            let s = (BOLTZ * t / (m * MVV2E)).sqrt();
            [normal(rng) * s, normal(rng) * s, normal(rng) * s]
        })
        .collect();
    remove_momentum(&mut v, masses);
    let ke: f64 = 0.5 * MVV2E * v.iter().zip(masses).map(|(vi, m)| m * (vi[0] * vi[0] + vi[1] * vi[1] + vi[2] * vi[2])).sum::<f64>();
    let dof = (3 * n).saturating_sub(3) as f64;
    if ke > 0.0 && dof > 0.0 {
        let scale = (0.5 * dof * BOLTZ * t / ke).sqrt();
        for vi in &mut v {
            for c in vi.iter_mut() {
                *c *= scale;
            }
        }
    }
    v
}

/// Subtract the mass-weighted mean velocity.
pub fn remove_momentum(v: &mut [[f64; 3]], masses: &[f64]) {
    let mt: f64 = masses.iter().sum();
    let mut p = [0.0; 3];
    for (vi, m) in v.iter().zip(masses) {
        for d in 0..3 {
            p[d] += m * vi[d];
        }
    }
    for vi in v.iter_mut() {
        for d in 0..3 {
            vi[d] -= p[d] / mt;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Nearest-neighbour distances of every atom (periodic minimum image), sorted.
    fn neighbour_counts(x: &[[f64; 3]], l: [f64; 3], r: f64) -> Vec<usize> {
        x.iter()
            .map(|a| {
                x.iter()
                    .filter(|b| {
                        let d2: f64 = (0..3)
                            .map(|k| {
                                let mut d = a[k] - b[k];
                                d -= l[k] * (d / l[k]).round();
                                d * d
                            })
                            .sum();
                        d2 > 1e-12 && (d2.sqrt() - r).abs() < 1e-9
                    })
                    .count()
            })
            .collect()
    }

    #[test]
    fn oriented_boxes_hold_whole_cells_of_the_same_crystal() {
        let a0 = 3.615;
        // Cells chosen so every box side exceeds twice the shell radius (unique minimum images).
        for (kind, o, cells, per_cell, shell) in [
            (LatticeKind::Fcc, [[1, 1, 0], [-1, 1, 0], [0, 0, 1]], [2, 2, 2], 8, (12, a0 / 2f64.sqrt())),
            (LatticeKind::Fcc, [[1, 1, 1], [-1, 1, 0], [-1, -1, 2]], [1, 2, 1], 24, (12, a0 / 2f64.sqrt())),
            (LatticeKind::Bcc, [[1, 1, 1], [-1, 1, 0], [-1, -1, 2]], [2, 2, 1], 12, (8, a0 * 3f64.sqrt() / 2.0)),
            (LatticeKind::Sc, [[2, 1, 0], [-1, 2, 0], [0, 0, 1]], [1, 1, 3], 5, (6, a0)),
        ] {
            let orient = Orientation(o);
            assert_eq!(kind.atoms_per_cell(&orient), per_cell, "{o:?}");
            let (x, l) = build_oriented(kind, a0, cells, &orient).unwrap();
            let n_cells: usize = cells.iter().product();
            assert_eq!(x.len() as u64, n_cells as u64 * per_cell, "{kind:?} {o:?}");
            for k in 0..3 {
                assert!((l[k] - cells[k] as f64 * a0 * orient.period(k)).abs() < 1e-12);
                assert!(l[k] > 2.0 * shell.1, "test box too small");
                assert!(x.iter().all(|p| p[k] >= 0.0 && p[k] < l[k]), "{o:?}: an atom outside the box");
            }
            // Every atom sees the bulk coordination at the nearest-neighbour distance: the box
            // is a periodic piece of the perfect crystal (no gap, no overlap at the faces).
            let counts = neighbour_counts(&x, l, shell.1);
            assert!(counts.iter().all(|&n| n == shell.0), "{kind:?} {o:?}: {counts:?}");
        }
    }

    #[test]
    fn the_cube_orientation_is_the_plain_lattice_and_bad_orientations_are_named() {
        let plain = build_lattice(LatticeKind::Fcc, 3.615, [2, 3, 1]);
        assert_eq!(build_oriented(LatticeKind::Fcc, 3.615, [2, 3, 1], &Orientation::CUBE).unwrap(), plain);
        for (o, msg) in [
            ([[1, 1, 0], [1, 1, 0], [0, 0, 1]], "not orthogonal"),
            ([[1, 1, 0], [1, -1, 0], [0, 0, 1]], "left-handed"),
            ([[0, 0, 0], [0, 1, 0], [0, 0, 1]], "x direction is zero"),
            ([[13, 0, 0], [0, 1, 0], [0, 0, 1]], "-12..=12"),
        ] {
            let e = build_oriented(LatticeKind::Fcc, 3.615, [1; 3], &Orientation(o)).unwrap_err().to_string();
            assert!(e.contains(msg), "{o:?}: {e}");
        }
        assert_eq!("1,1,0/-1,1,0/0,0,1".parse::<Orientation>().unwrap(), Orientation([[1, 1, 0], [-1, 1, 0], [0, 0, 1]]));
        for bad in ["1,1,0/-1,1,0", "1,1/-1,1,0/0,0,1", "a,1,0/-1,1,0/0,0,1"] {
            assert!(bad.parse::<Orientation>().unwrap_err().to_string().contains("expected three directions"), "{bad}");
        }
        assert!("1,1,0/1,-1,0/0,0,1".parse::<Orientation>().unwrap_err().to_string().contains("left-handed"));
    }
}
