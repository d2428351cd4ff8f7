//! LAMMPS data files (`atom_style atomic`, orthogonal boxes, optional `Masses` and
//! `Velocities`) and LAMMPS text dumps (readable by OVITO).

use crate::backend::{BoxSpec, InitialAtoms, PointId};
use crate::error::MdError;
use crate::lattice::LatticeKind;
use std::fmt::Write as _;

/// Atoms of a LAMMPS data file, sorted by atom id.
#[derive(Debug, Clone, PartialEq)]
pub struct DataFile {
    /// Lower box corner (A).
    pub lo: [f64; 3],
    /// Box lengths (A).
    pub lengths: [f64; 3],
    /// Atom ids, ascending.
    pub ids: Vec<u64>,
    /// LAMMPS atom type (1-based) per atom.
    pub types: Vec<u32>,
    /// Positions (A).
    pub x: Vec<[f64; 3]>,
    /// Velocities (A/ps); zero when the file has none.
    pub v: Vec<[f64; 3]>,
    /// Masses per type (index type - 1) when the file has a `Masses` section.
    pub masses: Option<Vec<f64>>,
}

fn perr(file: &str, line: usize, msg: impl Into<String>) -> MdError {
    MdError::Parse { file: file.to_string(), line, msg: msg.into() }
}

fn num<T: std::str::FromStr>(file: &str, ln: usize, tok: Option<&str>, what: &str) -> Result<T, MdError> {
    let tok = tok.ok_or_else(|| perr(file, ln, format!("expected {what}, found end of line")))?;
    tok.parse().map_err(|_| perr(file, ln, format!("expected {what}, found {tok:?}")))
}

/// A finite number (`nan` and `inf` parse as f64 but are no coordinate).
fn real(file: &str, ln: usize, tok: Option<&str>, what: &str) -> Result<f64, MdError> {
    let v: f64 = num(file, ln, tok, what)?;
    if v.is_finite() { Ok(v) } else { Err(perr(file, ln, format!("{what} = {v} is not a finite number"))) }
}

impl DataFile {
    /// Read a data file from disk.
    pub fn read(path: &std::path::Path) -> Result<Self, MdError> {
        let name = path.to_string_lossy().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| MdError::Io { file: name.clone(), source: e })?;
        Self::parse(&text, &name)
    }

    /// Parse data-file text (`file` names it in errors).
    pub fn parse(text: &str, file: &str) -> Result<Self, MdError> {
        let lines: Vec<&str> = text.lines().map(|l| l.split('#').next().unwrap_or("").trim()).collect();
        let (mut natoms, mut ntypes) = (None, 1u32);
        let mut lo = [f64::NAN; 3];
        let mut hi = [f64::NAN; 3];
        let mut k = 1; // first line is a title
        while k < lines.len() {
            let l = lines[k];
            let w: Vec<&str> = l.split_whitespace().collect();
            if l.is_empty() {
                k += 1;
                continue;
            }
            let ln = k + 1;
            if l.ends_with(" atoms") && w.len() == 2 {
                natoms = Some(num::<usize>(file, ln, w.first().copied(), "the atom count")?);
            } else if l.ends_with("atom types") {
                ntypes = num(file, ln, w.first().copied(), "the atom type count")?;
            } else if w.len() == 4 && ["xhi", "yhi", "zhi"].contains(&w[3]) {
                let d = (w[3].as_bytes()[0] - b'x') as usize;
                lo[d] = real(file, ln, Some(w[0]), &format!("the box lower bound {}", w[2]))?;
                hi[d] = real(file, ln, Some(w[1]), &format!("the box upper bound {}", w[3]))?;
            } else if l.ends_with("xy xz yz") {
                return Err(MdError::Unsupported(format!("{file}:{ln}: triclinic boxes (xy xz yz) are not supported")));
            } else if l.ends_with(" bonds") || l.ends_with(" angles") || l.contains("types") {
                // ignore counts of other things
            } else {
                break;
            }
            k += 1;
        }
        let n = natoms.ok_or_else(|| perr(file, k + 1, "expected an 'N atoms' header line before the sections"))?;
        if lo.iter().chain(hi.iter()).any(|v| v.is_nan()) {
            return Err(perr(file, k + 1, "expected 'xlo xhi', 'ylo yhi' and 'zlo zhi' header lines"));
        }
        let lengths = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
        if lengths.iter().any(|l| !(*l > 0.0)) {
            return Err(perr(file, k + 1, format!("box bounds must have hi > lo, got lengths {lengths:?}")));
        }
        let mut atoms: Vec<(u64, u32, [f64; 3])> = Vec::new();
        let mut vels: Vec<(u64, [f64; 3])> = Vec::new();
        let mut masses = None;
        while k < lines.len() {
            let head = lines[k].split_whitespace().next().unwrap_or("");
            if head.is_empty() {
                k += 1;
                continue;
            }
            let rows = match head {
                "Atoms" => n,
                "Velocities" => n,
                "Masses" => ntypes as usize,
                other => return Err(perr(file, k + 1, format!("unsupported section {other:?} (expected Masses, Atoms or Velocities)"))),
            };
            k += 1;
            let mut got = 0;
            if head == "Masses" && rows > lines.len() - k {
                // Before the table is allocated: "4294967295 atom types" is a broken header.
                return Err(perr(
                    file,
                    lines.len() + 1,
                    format!("unexpected end of file: section Masses expects {rows} lines, the file has {} more", lines.len() - k),
                ));
            }
            let mut m = if head == "Masses" { vec![0.0; ntypes as usize] } else { Vec::new() };
            while got < rows {
                if k >= lines.len() {
                    return Err(perr(file, k + 1, format!("unexpected end of file: section {head} expects {rows} lines, found {got}")));
                }
                let l = lines[k];
                k += 1;
                if l.is_empty() {
                    continue;
                }
                let ln = k;
                let mut w = l.split_whitespace();
                match head {
                    "Atoms" => {
                        let id: u64 = num(file, ln, w.next(), "atom id")?;
                        let t: u32 = num(file, ln, w.next(), "atom type")?;
                        if t == 0 || t > ntypes {
                            return Err(perr(file, ln, format!("atom type {t} out of range 1..={ntypes}")));
                        }
                        let what = |c: &str| format!("{c} of atom {id}");
                        let p: [f64; 3] = [
                            real(file, ln, w.next(), &what("x"))?,
                            real(file, ln, w.next(), &what("y"))?,
                            real(file, ln, w.next(), &what("z"))?,
                        ];
                        // optional image flags
                        let mut img = [0.0; 3];
                        for c in &mut img {
                            if let Some(tok) = w.next() {
                                *c = num::<i64>(file, ln, Some(tok), "an image flag")? as f64;
                            }
                        }
                        let p = [p[0] + img[0] * lengths[0], p[1] + img[1] * lengths[1], p[2] + img[2] * lengths[2]];
                        for d in 0..3 {
                            let outside = if p[d] < lo[d] { (lo[d] - p[d]) / lengths[d] } else { (p[d] - lo[d]) / lengths[d] - 1.0 };
                            if !(outside <= crate::backend::MAX_BOX_LENGTHS_OUTSIDE) {
                                let c = ["x", "y", "z"][d];
                                return Err(perr(
                                    file,
                                    ln,
                                    format!(
                                        "atom {id}: {c} = {} A (with its image flag) lies {outside:.3e} box lengths outside {c}lo {c}hi = [{}, {}]; \
                                         at most {} are wrapped in",
                                        crate::error::show(p[d]),
                                        lo[d],
                                        hi[d],
                                        crate::backend::MAX_BOX_LENGTHS_OUTSIDE
                                    ),
                                ));
                            }
                        }
                        atoms.push((id, t, p));
                    }
                    "Velocities" => {
                        let id: u64 = num(file, ln, w.next(), "atom id")?;
                        let what = |c: &str| format!("{c} of atom {id}");
                        vels.push((
                            id,
                            [
                                real(file, ln, w.next(), &what("vx"))?,
                                real(file, ln, w.next(), &what("vy"))?,
                                real(file, ln, w.next(), &what("vz"))?,
                            ],
                        ));
                    }
                    _ => {
                        let t: usize = num(file, ln, w.next(), "atom type")?;
                        if t == 0 || t > ntypes as usize {
                            return Err(perr(file, ln, format!("mass for type {t} out of range 1..={ntypes}")));
                        }
                        m[t - 1] = real(file, ln, w.next(), "mass")?;
                    }
                }
                got += 1;
            }
            if head == "Masses" {
                masses = Some(m);
            }
        }
        if atoms.len() != n {
            return Err(perr(file, lines.len() + 1, format!("expected an Atoms section with {n} atoms")));
        }
        atoms.sort_by_key(|a| a.0);
        vels.sort_by_key(|a| a.0);
        if atoms.windows(2).any(|w| w[0].0 == w[1].0) {
            return Err(perr(file, 0, "duplicate atom ids"));
        }
        let v = if vels.is_empty() {
            vec![[0.0; 3]; n]
        } else {
            if vels.iter().map(|a| a.0).ne(atoms.iter().map(|a| a.0)) {
                return Err(perr(file, 0, "Velocities section ids do not match the Atoms section ids"));
            }
            vels.iter().map(|a| a.1).collect()
        };
        Ok(DataFile {
            lo,
            lengths,
            ids: atoms.iter().map(|a| a.0).collect(),
            types: atoms.iter().map(|a| a.1).collect(),
            x: atoms.iter().map(|a| a.2).collect(),
            v,
            masses,
        })
    }

    /// A box spec of point `id` holding exactly these atoms (types 1.. become the potential's
    /// elements 0.., velocities kept), the other settings those of `BoxSpec::lattice`.
    pub fn box_spec(&self, id: PointId) -> BoxSpec {
        let mut s = BoxSpec::lattice(id, LatticeKind::Fcc, 1.0, [1, 1, 1]);
        s.atoms = InitialAtoms::Explicit {
            lo: self.lo,
            lengths: self.lengths,
            types: self.types.iter().map(|t| t - 1).collect(),
            x: self.x.clone(),
            v: self.v.clone(),
        };
        s
    }

    /// LAMMPS data-file text (%.17g, round-trips exactly).
    pub fn to_text(&self, title: &str) -> String {
        let mut s = String::new();
        // As many types as masses are written (a type may have no atom; found by fuzzing).
        let ntypes = self.types.iter().copied().max().unwrap_or(1).max(self.masses.as_ref().map_or(0, |m| m.len() as u32));
        let _ = writeln!(s, "{title}\n\n{} atoms\n{ntypes} atom types\n", self.x.len());
        for (d, ax) in ["x", "y", "z"].iter().enumerate() {
            let _ = writeln!(s, "{:e} {:e} {ax}lo {ax}hi", self.lo[d], self.lo[d] + self.lengths[d]);
        }
        if let Some(m) = &self.masses {
            let _ = writeln!(s, "\nMasses\n");
            for (t, mt) in m.iter().enumerate() {
                let _ = writeln!(s, "{} {mt:e}", t + 1);
            }
        }
        let _ = writeln!(s, "\nAtoms # atomic\n");
        for ((id, t), p) in self.ids.iter().zip(&self.types).zip(&self.x) {
            let _ = writeln!(s, "{id} {t} {:e} {:e} {:e}", p[0], p[1], p[2]);
        }
        let _ = writeln!(s, "\nVelocities\n");
        for (id, v) in self.ids.iter().zip(&self.v) {
            let _ = writeln!(s, "{id} {:e} {:e} {:e}", v[0], v[1], v[2]);
        }
        s
    }
}

/// One LAMMPS text dump frame (`id type x y z vx vy vz`), readable by OVITO.
pub fn dump_frame(step: u64, lo: [f64; 3], l: [f64; 3], ids: &[u64], types: &[u32], x: &[[f64; 3]], v: &[[f64; 3]]) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "ITEM: TIMESTEP\n{step}\nITEM: NUMBER OF ATOMS\n{}\nITEM: BOX BOUNDS pp pp pp", x.len());
    for d in 0..3 {
        let _ = writeln!(s, "{:e} {:e}", lo[d], lo[d] + l[d]);
    }
    let _ = writeln!(s, "ITEM: ATOMS id type x y z vx vy vz");
    for k in 0..x.len() {
        let (p, u) = (x[k], v[k]);
        let _ = writeln!(s, "{} {} {:e} {:e} {:e} {:e} {:e} {:e}", ids[k], types[k], p[0], p[1], p[2], u[0], u[1], u[2]);
    }
    s
}
