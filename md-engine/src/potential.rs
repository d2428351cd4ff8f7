//! Interatomic potentials: EAM from LAMMPS `funcfl` (`.eam`), `setfl` (`.eam.alloy`) and
//! Finnis-Sinclair (`.eam.fs`) files, tabulated and splined exactly as LAMMPS `pair_eam`
//! does (`file2array` + `array2spline`), and `lj/cut` for tests.
//!
//! Element indices are 0-based; an atom's `type` in the engine is its element index.

use crate::error::MdError;
use std::path::Path;

/// A pair of (element names, masses) plus the tables of one potential.
#[derive(Debug, Clone)]
pub enum Potential {
    /// Embedded-atom method, any of the three LAMMPS file formats.
    Eam(EamTables),
    /// Lennard-Jones 12-6, cut at `cutoff` (not shifted, as LAMMPS `lj/cut`).
    LjCut(LjCut),
}

/// Lennard-Jones parameters (one element).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LjCut {
    /// Well depth (eV).
    pub epsilon: f64,
    /// Zero crossing (A).
    pub sigma: f64,
    /// Cut-off radius (A).
    pub cutoff: f64,
    /// Atom mass (amu).
    pub mass: f64,
}

impl Potential {
    /// Read an EAM potential file; the format follows the name: `*.eam.alloy`/`*.setfl`
    /// (setfl), `*.eam.fs` (Finnis-Sinclair), otherwise `*.eam` (funcfl).
    pub fn from_file(path: &Path) -> Result<Self, MdError> {
        let name = path.to_string_lossy().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| MdError::Io { file: name.clone(), source: e })?;
        Self::from_text(&name, &text)
    }

    /// Parse potential text; `name` (a file name) decides the format as in [`Potential::from_file`].
    pub fn from_text(name: &str, text: &str) -> Result<Self, MdError> {
        let name = name.to_string();
        let fmt = if name.ends_with(".eam.alloy") || name.ends_with(".setfl") {
            EamFormat::Setfl
        } else if name.ends_with(".eam.fs") {
            EamFormat::FinnisSinclair
        } else if name.ends_with(".eam") {
            EamFormat::Funcfl
        } else {
            return Err(MdError::invalid(
                "potential file name",
                format!("{name}: cannot tell the format; expected a name ending in .eam, .eam.alloy, .setfl or .eam.fs"),
            ));
        };
        Ok(Potential::Eam(EamTables::parse(text, &name, fmt)?))
    }

    /// Interaction cut-off (A).
    pub fn cutoff(&self) -> f64 {
        match self {
            Potential::Eam(t) => t.cutoff,
            Potential::LjCut(lj) => lj.cutoff,
        }
    }

    /// Number of elements (atom types) the potential describes.
    pub fn n_elements(&self) -> usize {
        match self {
            Potential::Eam(t) => t.masses.len(),
            Potential::LjCut(_) => 1,
        }
    }

    /// Mass of element `e` (amu).
    pub fn mass(&self, e: usize) -> f64 {
        match self {
            Potential::Eam(t) => t.masses[e],
            Potential::LjCut(lj) => lj.mass,
        }
    }

    /// The LAMMPS pair style name this potential corresponds to.
    pub fn style(&self) -> &'static str {
        match self {
            Potential::Eam(t) => match t.format {
                EamFormat::Funcfl => "eam",
                EamFormat::Setfl => "eam/alloy",
                EamFormat::FinnisSinclair => "eam/fs",
            },
            Potential::LjCut(_) => "lj/cut",
        }
    }
}

/// The three LAMMPS EAM file formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EamFormat {
    /// DYNAMO funcfl (`pair_style eam`): F(rho), Z(r), rho(r) for one element.
    Funcfl,
    /// DYNAMO setfl (`pair_style eam/alloy`).
    Setfl,
    /// Finnis-Sinclair setfl variant (`pair_style eam/fs`).
    FinnisSinclair,
}

/// One cubic spline table in the LAMMPS layout: `s[m]` for m = 1..=n holds 7 coefficients
/// (0..=2: derivative, 3..=6: value); index 0 is unused, as in LAMMPS.
pub type Spline = Vec<[f64; 7]>;

/// EAM tables on LAMMPS's common grids, splined as `PairEAM::array2spline`.
#[derive(Debug, Clone)]
pub struct EamTables {
    /// Which file format they came from.
    pub format: EamFormat,
    /// Element names (funcfl: the atomic number as text).
    pub elements: Vec<String>,
    /// Masses (amu), per element.
    pub masses: Vec<f64>,
    pub(crate) nrho: usize,
    pub(crate) nr: usize,
    pub(crate) rdr: f64,
    pub(crate) rdrho: f64,
    pub(crate) rhomax: f64,
    /// Cut-off (A).
    pub cutoff: f64,
    pub(crate) cutforcesq: f64,
    pub(crate) frho: Vec<Spline>,
    pub(crate) rhor: Vec<Spline>,
    pub(crate) z2r: Vec<Spline>,
    /// type2rhor[i][j]: which rhor spline, as LAMMPS.
    pub(crate) type2rhor: Vec<Vec<usize>>,
    pub(crate) type2z2r: Vec<Vec<usize>>,
}

/// A reader of whitespace-separated numbers spanning lines, tracking line numbers.
struct Reader<'a> {
    lines: Vec<&'a str>,
    next: usize,
    file: &'a str,
}

impl<'a> Reader<'a> {
    fn err(&self, line: usize, msg: String) -> MdError {
        MdError::Parse { file: self.file.to_string(), line, msg }
    }
    fn line(&mut self, what: &str) -> Result<(usize, &'a str), MdError> {
        if self.next >= self.lines.len() {
            return Err(self.err(self.next + 1, format!("unexpected end of file: expected {what}")));
        }
        self.next += 1;
        Ok((self.next, self.lines[self.next - 1]))
    }
    /// `n` numbers, read from whole lines (extra numbers at the end of the last line ignored).
    fn values(&mut self, n: usize, what: &str) -> Result<Vec<f64>, MdError> {
        let mut out = Vec::with_capacity(n);
        while out.len() < n {
            if self.next >= self.lines.len() {
                return Err(self.err(
                    self.next + 1,
                    format!("unexpected end of file: expected {n} values of {what}, found {}", out.len()),
                ));
            }
            let (ln, text) = self.line(what)?;
            for tok in text.split_whitespace() {
                if out.len() == n {
                    break;
                }
                let v: f64 = parse_f64(tok).ok_or_else(|| {
                    self.err(ln, format!("expected a number ({what}, value {} of {n}), found {tok:?}", out.len() + 1))
                })?;
                out.push(v);
            }
        }
        Ok(out)
    }
}

fn parse_f64(tok: &str) -> Option<f64> {
    // DYNAMO files sometimes use Fortran `D` exponents.
    let v: f64 = tok.replace(['D', 'd'], "e").parse().ok()?;
    v.is_finite().then_some(v)
}

fn parse_tok<T: std::str::FromStr>(r: &Reader, ln: usize, tok: Option<&str>, what: &str) -> Result<T, MdError> {
    let tok = tok.ok_or_else(|| r.err(ln, format!("expected {what}, found end of line")))?;
    let t = if std::any::type_name::<T>() == "f64" { tok.replace(['D', 'd'], "e") } else { tok.to_string() };
    t.parse::<T>().map_err(|_| r.err(ln, format!("expected {what}, found {tok:?}")))
}

/// Grid header "nrho drho nr dr cut".
struct Grid {
    nrho: usize,
    drho: f64,
    nr: usize,
    dr: f64,
    cut: f64,
}

fn read_grid(r: &mut Reader) -> Result<Grid, MdError> {
    let (ln, text) = r.line("the grid line 'Nrho drho Nr dr cutoff'")?;
    let mut it = text.split_whitespace();
    let g = Grid {
        nrho: parse_tok(r, ln, it.next(), "Nrho (integer)")?,
        drho: parse_tok(r, ln, it.next(), "drho (number)")?,
        nr: parse_tok(r, ln, it.next(), "Nr (integer)")?,
        dr: parse_tok(r, ln, it.next(), "dr (number)")?,
        cut: parse_tok(r, ln, it.next(), "cutoff (number)")?,
    };
    if g.nrho < 5 || g.nr < 5 || !(g.drho > 0.0) || !(g.dr > 0.0) || !(g.cut > 0.0) {
        return Err(r.err(ln, "grid needs Nrho >= 5, Nr >= 5 and positive drho, dr, cutoff".into()));
    }
    Ok(g)
}

/// 1-indexed copy of a table (index 0 unused), as LAMMPS stores them.
fn one_indexed(v: Vec<f64>) -> Vec<f64> {
    let mut out = Vec::with_capacity(v.len() + 1);
    out.push(0.0);
    out.extend(v);
    out
}

/// LAMMPS `PairEAM::interpolate`: 1-indexed table f[1..=n] to 7-coefficient spline.
fn interpolate(n: usize, delta: f64, f: &[f64]) -> Spline {
    let mut s = vec![[0.0f64; 7]; n + 1];
    for m in 1..=n {
        s[m][6] = f[m];
    }
    s[1][5] = s[2][6] - s[1][6];
    s[2][5] = 0.5 * (s[3][6] - s[1][6]);
    s[n - 1][5] = 0.5 * (s[n][6] - s[n - 2][6]);
    s[n][5] = s[n][6] - s[n - 1][6];
    for m in 3..=n - 2 {
        s[m][5] = ((s[m - 2][6] - s[m + 2][6]) + 8.0 * (s[m + 1][6] - s[m - 1][6])) / 12.0;
    }
    for m in 1..n {
        s[m][4] = 3.0 * (s[m + 1][6] - s[m][6]) - 2.0 * s[m][5] - s[m + 1][5];
        s[m][3] = s[m][5] + s[m + 1][5] - 2.0 * (s[m + 1][6] - s[m][6]);
    }
    s[n][4] = 0.0;
    s[n][3] = 0.0;
    for sm in s.iter_mut().skip(1) {
        sm[2] = sm[5] / delta;
        sm[1] = 2.0 * sm[4] / delta;
        sm[0] = 3.0 * sm[3] / delta;
    }
    s
}

/// LAMMPS's 4-point Lagrange resampling of a funcfl table onto the common grid.
fn resample(file: &[f64], file_n: usize, file_d: f64, n: usize, d: f64) -> Vec<f64> {
    const SIXTH: f64 = 1.0 / 6.0;
    let mut out = vec![0.0; n + 1];
    for (m, o) in out.iter_mut().enumerate().skip(1) {
        let r = (m - 1) as f64 * d;
        let mut p = r / file_d + 1.0;
        let mut k = p as usize;
        k = k.min(file_n - 2).max(2);
        p -= k as f64;
        p = p.min(2.0);
        let c1 = -SIXTH * p * (p - 1.0) * (p - 2.0);
        let c2 = 0.5 * (p * p - 1.0) * (p - 2.0);
        let c3 = -0.5 * p * (p + 1.0) * (p - 2.0);
        let c4 = SIXTH * p * (p * p - 1.0);
        *o = c1 * file[k - 1] + c2 * file[k] + c3 * file[k + 1] + c4 * file[k + 2];
    }
    out
}

impl EamTables {
    /// Parse a potential file's text (`file` names it in errors).
    pub fn parse(text: &str, file: &str, format: EamFormat) -> Result<Self, MdError> {
        let mut r = Reader { lines: text.lines().collect(), next: 0, file };
        match format {
            EamFormat::Funcfl => Self::parse_funcfl(&mut r),
            _ => Self::parse_setfl(&mut r, format),
        }
    }

    fn parse_funcfl(r: &mut Reader) -> Result<Self, MdError> {
        r.line("a comment line")?;
        let (ln, text) = r.line("the element line 'atomic-number mass'")?;
        let mut it = text.split_whitespace();
        let z: String = parse_tok(r, ln, it.next(), "the atomic number")?;
        let mass: f64 = parse_tok(r, ln, it.next(), "the mass (number)")?;
        let g = read_grid(r)?;
        let frho = one_indexed(r.values(g.nrho, "F(rho)")?);
        let zr = one_indexed(r.values(g.nr, "Z(r)")?);
        let rhor = one_indexed(r.values(g.nr, "rho(r)")?);
        // PairEAM::file2array, funcfl branch, with one active file.
        let rmax = (g.nr - 1) as f64 * g.dr;
        let rhomax = (g.nrho - 1) as f64 * g.drho;
        let nr = (rmax / g.dr + 0.5) as usize;
        let nrho = (rhomax / g.drho + 0.5) as usize;
        let frho_c = resample(&frho, g.nrho, g.drho, nrho, g.drho);
        let rhor_c = resample(&rhor, g.nr, g.dr, nr, g.dr);
        let zr_c = resample(&zr, g.nr, g.dr, nr, g.dr);
        let z2r: Vec<f64> = zr_c.iter().map(|z| 27.2 * 0.529 * z * z).collect();
        Ok(Self::finish(
            EamFormat::Funcfl,
            vec![z],
            vec![mass],
            (nrho, g.drho, nr, g.dr, rhomax, g.cut),
            vec![frho_c],
            vec![rhor_c],
            vec![z2r],
            vec![vec![0]],
            vec![vec![0]],
        ))
    }

    fn parse_setfl(r: &mut Reader, format: EamFormat) -> Result<Self, MdError> {
        for _ in 0..3 {
            r.line("one of three comment lines")?;
        }
        let (ln, text) = r.line("the elements line 'N name1 ... nameN'")?;
        let mut it = text.split_whitespace();
        let ne: usize = parse_tok(r, ln, it.next(), "the number of elements (integer)")?;
        let elements: Vec<String> = it.map(str::to_string).collect();
        if ne == 0 || elements.len() != ne {
            return Err(r.err(ln, format!("expected {ne} element names after the count, found {}", elements.len())));
        }
        let g = read_grid(r)?;
        let (mut frho, mut rhor, mut masses) = (Vec::new(), Vec::new(), Vec::new());
        for e in &elements {
            let (ln, text) = r.line(&format!("the header line of element {e} 'Z mass a lattice'"))?;
            let mut it = text.split_whitespace();
            let _z: String = parse_tok(r, ln, it.next(), "the atomic number")?;
            masses.push(parse_tok::<f64>(r, ln, it.next(), "the mass (number)")?);
            frho.push(one_indexed(r.values(g.nrho, &format!("F(rho) of {e}"))?));
            let nden = if format == EamFormat::FinnisSinclair { ne } else { 1 };
            for j in 0..nden {
                rhor.push(one_indexed(r.values(g.nr, &format!("rho(r) of {e} (table {})", j + 1))?));
            }
        }
        let mut z2r = Vec::new();
        for i in 0..ne {
            for j in 0..=i {
                z2r.push(one_indexed(
                    r.values(g.nr, &format!("r*phi(r) of {}-{}", elements[i], elements[j]))?,
                ));
            }
        }
        let type2rhor: Vec<Vec<usize>> = (0..ne)
            .map(|i| (0..ne).map(|j| if format == EamFormat::FinnisSinclair { i * ne + j } else { i }).collect())
            .collect();
        let type2z2r: Vec<Vec<usize>> = (0..ne)
            .map(|i| (0..ne).map(|j| { let (a, b) = (i.max(j), i.min(j)); a * (a + 1) / 2 + b }).collect())
            .collect();
        let rhomax = (g.nrho - 1) as f64 * g.drho;
        Ok(Self::finish(format, elements, masses, (g.nrho, g.drho, g.nr, g.dr, rhomax, g.cut), frho, rhor, z2r, type2rhor, type2z2r))
    }

    #[allow(clippy::too_many_arguments)]
    fn finish(
        format: EamFormat,
        elements: Vec<String>,
        masses: Vec<f64>,
        (nrho, drho, nr, dr, rhomax, cut): (usize, f64, usize, f64, f64, f64),
        frho: Vec<Vec<f64>>,
        rhor: Vec<Vec<f64>>,
        z2r: Vec<Vec<f64>>,
        type2rhor: Vec<Vec<usize>>,
        type2z2r: Vec<Vec<usize>>,
    ) -> Self {
        EamTables {
            format,
            elements,
            masses,
            nrho,
            nr,
            rdr: 1.0 / dr,
            rdrho: 1.0 / drho,
            rhomax,
            cutoff: cut,
            cutforcesq: cut * cut,
            frho: frho.iter().map(|f| interpolate(nrho, drho, f)).collect(),
            rhor: rhor.iter().map(|f| interpolate(nr, dr, f)).collect(),
            z2r: z2r.iter().map(|f| interpolate(nr, dr, f)).collect(),
            type2rhor,
            type2z2r,
        }
    }

    /// Squared force cut-off (A^2).
    #[inline]
    pub fn cutforcesq(&self) -> f64 {
        self.cutforcesq
    }

    #[inline]
    fn r_index(&self, r: f64) -> (usize, f64) {
        let p = r * self.rdr + 1.0;
        let m = (p as usize).min(self.nr - 1);
        (m, (p - m as f64).min(1.0))
    }

    /// Density at an atom of element `i` due to a neighbour of element `j` at distance `r`.
    #[inline]
    pub fn density(&self, i: usize, j: usize, r: f64) -> f64 {
        let (m, p) = self.r_index(r);
        let c = &self.rhor[self.type2rhor[j][i]][m];
        ((c[3] * p + c[4]) * p + c[5]) * p + c[6]
    }

    /// Embedding energy (eV) and its derivative F'(rho) for element `e`, with LAMMPS's
    /// linear extrapolation beyond the table.
    #[inline]
    pub fn embed(&self, e: usize, rho: f64) -> (f64, f64) {
        let p = rho * self.rdrho + 1.0;
        let m = (p as usize).min(self.nrho - 1).max(1);
        let p = (p - m as f64).min(1.0);
        let c = &self.frho[e][m];
        let fp = (c[0] * p + c[1]) * p + c[2];
        let mut phi = ((c[3] * p + c[4]) * p + c[5]) * p + c[6];
        if rho > self.rhomax {
            phi += fp * (rho - self.rhomax);
        }
        (phi, fp)
    }

    /// Pair term between elements i and j at distance r: returns (phi, psip) where
    /// psip = dE/dr of the pair including both embedding terms, given F'(rho) of both.
    #[inline]
    pub fn pair(&self, i: usize, j: usize, r: f64, fp_i: f64, fp_j: f64) -> (f64, f64) {
        let (m, p) = self.r_index(r);
        let c = &self.rhor[self.type2rhor[i][j]][m];
        let rhoip = (c[0] * p + c[1]) * p + c[2];
        let c = &self.rhor[self.type2rhor[j][i]][m];
        let rhojp = (c[0] * p + c[1]) * p + c[2];
        let c = &self.z2r[self.type2z2r[i][j]][m];
        let z2p = (c[0] * p + c[1]) * p + c[2];
        let z2 = ((c[3] * p + c[4]) * p + c[5]) * p + c[6];
        let recip = 1.0 / r;
        let phi = z2 * recip;
        let phip = z2p * recip - phi * recip;
        (phi, fp_i * rhojp + fp_j * rhoip + phip)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn spline_reproduces_a_cubic_between_knots() {
        // The 7-coefficient scheme is exact for quadratics in the interior.
        let n = 20;
        let d = 0.1;
        let f: Vec<f64> = (0..=n).map(|m| if m == 0 { 0.0 } else { let x = (m - 1) as f64 * d; 1.0 + 2.0 * x + 3.0 * x * x }).collect();
        let s = interpolate(n, d, &f);
        let m = 8;
        let p = 0.37;
        let x = (m as f64 - 1.0 + p) * d;
        let c = &s[m];
        let val = ((c[3] * p + c[4]) * p + c[5]) * p + c[6];
        let der = (c[0] * p + c[1]) * p + c[2];
        assert!((val - (1.0 + 2.0 * x + 3.0 * x * x)).abs() < 1e-12, "{val}");
        assert!((der - (2.0 + 6.0 * x)).abs() < 1e-10, "{der}");
    }

    #[test]
    fn truncated_file_names_file_line_and_expectation() {
        let text = "comment\n29 63.55 3.615 FCC\n10 0.1 10 0.5 4.5\n1 2 3 4 5\n6 7\n";
        let err = EamTables::parse(text, "bad.eam", EamFormat::Funcfl).unwrap_err().to_string();
        assert!(err.contains("bad.eam:6"), "{err}");
        assert!(err.contains("10 values of F(rho)"), "{err}");
        let err = EamTables::parse("c\n29 63.5\n10 x 10 0.5 4.5\n", "b.eam", EamFormat::Funcfl).unwrap_err().to_string();
        assert!(err.contains("b.eam:3") && err.contains("drho"), "{err}");
    }
}
