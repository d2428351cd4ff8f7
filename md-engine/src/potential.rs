//! Interatomic potentials: EAM from LAMMPS `funcfl` (`.eam`), `setfl` (`.eam.alloy`) and
//! Finnis-Sinclair (`.eam.fs`) files, tabulated and splined exactly as LAMMPS `pair_eam`
//! does (`file2array` + `array2spline`), and `lj/cut` for tests.
//!
//! Element indices are 0-based; an atom's `type` in the engine is its element index.

use crate::error::MdError;
use std::path::Path;

/// A pair of (element names, masses) plus the tables of one potential.
// One potential per run, behind an Arc: the size of the EAM variant (its cached vibration
// included) costs nothing, and boxing it would add an indirection to every table look-up.
#[allow(clippy::large_enum_variant)]
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

    /// The fastest nearest-neighbour vibration of the potential's elements (each in its own
    /// fcc lattice at the potential's energy minimum), from which the engine bounds the MD time
    /// step ([`Vibration::max_dt_ps`]). `None` when the potential has no bound minimum or no
    /// stiffness there (a null potential), in which case no time step is refused on this ground.
    /// Computed once per EAM potential (a few milliseconds), then cached.
    pub fn vibration(&self) -> Option<Vibration> {
        match self {
            Potential::Eam(t) => *t.vibration.get_or_init(|| t.compute_vibration()),
            Potential::LjCut(lj) => {
                // No scan: the fcc nearest-neighbour distance of LJ is the pair minimum to ~3 %.
                let (e, s) = (lj.epsilon, lj.sigma);
                let phi = |r: f64| if r < lj.cutoff { 4.0 * e * ((s / r).powi(12) - (s / r).powi(6)) } else { 0.0 };
                let r1 = 2f64.powf(1.0 / 6.0) * s;
                einstein(0, lj.mass, r1, lj.cutoff, &phi, &|_| 0.0, &|_| 0.0)
            }
        }
    }

    /// The largest MD time step (ps) this potential allows: a tenth of its fastest
    /// nearest-neighbour vibration period ([`Potential::vibration`]); `None`: no bound.
    pub fn max_time_step(&self) -> Option<f64> {
        self.vibration().map(|v| v.max_dt_ps())
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

/// MD steps per vibration period below which a time step is refused ([`Vibration::max_dt_ps`]).
/// Velocity Verlet is unstable above about period / 4.4 (2 / omega_max, omega_max ~ sqrt(2)
/// omega_Einstein in fcc); a tenth of the period leaves room for thermal anharmonicity.
pub const STEPS_PER_PERIOD: f64 = 10.0;

/// The nearest-neighbour vibration of one element of a potential, in its fcc lattice at the
/// potential's energy minimum: the Einstein frequency of one atom displaced in the frozen
/// lattice, from the pair and embedding curvature at the shell distances.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vibration {
    /// Element index (0-based) whose vibration is the fastest.
    pub element: usize,
    /// Mass of that element (amu).
    pub mass: f64,
    /// Nearest-neighbour distance at the energy minimum (A).
    pub nn_distance: f64,
    /// Vibration period (ps).
    pub period_ps: f64,
}

impl Vibration {
    /// The largest time step allowed: period / [`STEPS_PER_PERIOD`] (ps).
    pub fn max_dt_ps(&self) -> f64 {
        self.period_ps / STEPS_PER_PERIOD
    }
}

impl std::fmt::Display for Vibration {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "a tenth of the potential's nearest-neighbour vibration period {:.4} ps (element {}, mass {} amu, fcc neighbours at {:.3} A)",
            self.period_ps, self.element, self.mass, self.nn_distance
        )
    }
}

/// fcc shells in units of the nearest-neighbour distance, out to `reach`: (distance, count).
fn fcc_shells(reach: f64) -> Vec<(f64, f64)> {
    // fcc sites are the integer vectors with an even coordinate sum (units of a0 / 2); the
    // nearest neighbour is at sqrt(2).
    let reach = reach.clamp(1.0, 8.0); // shells beyond 8 neighbour distances add nothing here
    let nmax = (2.0 * reach * reach).floor() as i64;
    let m = (nmax as f64).sqrt().ceil() as i64;
    let mut count = std::collections::BTreeMap::<i64, f64>::new();
    for i in -m..=m {
        for j in -m..=m {
            for k in -m..=m {
                let n = i * i + j * j + k * k;
                if n > 0 && n <= nmax && (i + j + k) % 2 == 0 {
                    *count.entry(n).or_default() += 1.0;
                }
            }
        }
    }
    count.into_iter().map(|(n, c)| ((n as f64 / 2.0).sqrt(), c)).collect()
}

/// The Einstein vibration of an atom of mass `mass` in an fcc lattice of nearest-neighbour
/// distance `r1` under pair energy `phi`, density `rho` and embedding `embed`; `None` when
/// the lattice is not stiff (omega^2 <= 0 or not finite).
fn einstein(
    element: usize,
    mass: f64,
    r1: f64,
    cutoff: f64,
    phi: &dyn Fn(f64) -> f64,
    rho: &dyn Fn(f64) -> f64,
    embed: &dyn Fn(f64) -> f64,
) -> Option<Vibration> {
    let shells = fcc_shells(cutoff / r1);
    let h = 1e-3 * r1;
    let d1 = |f: &dyn Fn(f64) -> f64, r: f64| (f(r + h) - f(r - h)) / (2.0 * h);
    let d2 = |f: &dyn Fn(f64) -> f64, r: f64| (f(r + h) - 2.0 * f(r) + f(r - h)) / (h * h);
    let rho_bar: f64 = shells.iter().map(|&(d, c)| c * rho(d * r1)).sum();
    let hr = 1e-3 * rho_bar.abs().max(1e-6);
    let fp = (embed(rho_bar + hr) - embed(rho_bar - hr)) / (2.0 * hr);
    let fpp = (embed(rho_bar + hr) - 2.0 * embed(rho_bar) + embed(rho_bar - hr)) / (hr * hr);
    // Trace of the displaced atom's Hessian: the effective pair psi = phi + 2 F'(rho) rho gives
    // psi'' + 2 psi' / r per neighbour, the neighbours' embedding F'' rho'^2.
    let mut trace = 0.0;
    for &(d, c) in &shells {
        let r = d * r1;
        if r + h >= cutoff {
            continue;
        }
        let psi = |x: f64| phi(x) + 2.0 * fp * rho(x);
        trace += c * (d2(&psi, r) + 2.0 * d1(&psi, r) / r + fpp * d1(rho, r).powi(2));
    }
    let omega2 = trace / 3.0 / mass * crate::units::FTM2V;
    (omega2.is_finite() && omega2 > 0.0 && mass > 0.0).then(|| Vibration {
        element,
        mass,
        nn_distance: r1,
        period_ps: 2.0 * std::f64::consts::PI / omega2.sqrt(),
    })
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
    /// [`Potential::vibration`], computed on first use.
    pub(crate) vibration: std::sync::OnceLock<Option<Vibration>>,
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
        // Capacity by what the file can hold, not by its header: a count of 1e11 in a broken
        // header must be an "unexpected end of file", not an allocation of 800 GB.
        let mut out = Vec::with_capacity(n.min(1 << 16));
        while out.len() < n {
            if self.next >= self.lines.len() {
                return Err(self.err(self.next + 1, format!("unexpected end of file: expected {n} values of {what}, found {}", out.len())));
            }
            let (ln, text) = self.line(what)?;
            for tok in text.split_whitespace() {
                if out.len() == n {
                    break;
                }
                let v: f64 = parse_f64(tok)
                    .ok_or_else(|| self.err(ln, format!("expected a number ({what}, value {} of {n}), found {tok:?}", out.len() + 1)))?;
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
    if let Some((name, v)) = [("drho", g.drho), ("dr", g.dr), ("cutoff", g.cut)].into_iter().find(|(_, v)| !v.is_finite()) {
        return Err(r.err(ln, format!("grid {name} = {v} is not a finite number")));
    }
    // The force kernel converts r / dr (r below the cut-off) to an i32 unchecked.
    if !(g.cut / g.dr < (1u64 << 30) as f64) {
        return Err(r.err(ln, format!("cutoff / dr = {:e} rows; at most 2^30", g.cut / g.dr)));
    }
    // The tables must span a finite range: (N - 1) d = inf made funcfl's resampled table
    // length usize::MAX (found by fuzzing).
    if !((g.nrho - 1) as f64 * g.drho).is_finite() || !((g.nr - 1) as f64 * g.dr).is_finite() {
        return Err(r.err(
            ln,
            format!(
                "grid spans (Nrho - 1) drho = {:e} and (Nr - 1) dr = {:e}: not finite",
                (g.nrho - 1) as f64 * g.drho,
                (g.nr - 1) as f64 * g.dr
            ),
        ));
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
                z2r.push(one_indexed(r.values(g.nr, &format!("r*phi(r) of {}-{}", elements[i], elements[j]))?));
            }
        }
        let type2rhor: Vec<Vec<usize>> =
            (0..ne).map(|i| (0..ne).map(|j| if format == EamFormat::FinnisSinclair { i * ne + j } else { i }).collect()).collect();
        let type2z2r: Vec<Vec<usize>> = (0..ne)
            .map(|i| {
                (0..ne)
                    .map(|j| {
                        let (a, b) = (i.max(j), i.min(j));
                        a * (a + 1) / 2 + b
                    })
                    .collect()
            })
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
            vibration: std::sync::OnceLock::new(),
        }
    }

    /// The fastest element vibration ([`Potential::vibration`]): per element, the fcc lattice
    /// energy per atom is scanned for its minimum in nearest-neighbour distance, and the
    /// Einstein frequency taken there.
    fn compute_vibration(&self) -> Option<Vibration> {
        let cut = self.cutoff;
        let (lo, n) = (0.15 * cut, 1700);
        let shells = fcc_shells(1.0 / 0.15);
        let mut best: Option<Vibration> = None;
        for e in 0..self.masses.len() {
            let phi = |r: f64| if r < cut { self.pair(e, e, r, 0.0, 0.0).0 } else { 0.0 };
            let rho = |r: f64| if r < cut { self.density(e, e, r) } else { 0.0 };
            let embed = |x: f64| self.embed(e, x).0;
            let energy = |r1: f64| {
                let (mut dens, mut pair) = (0.0, 0.0);
                for &(d, c) in &shells {
                    let r = d * r1;
                    if r >= cut {
                        break;
                    }
                    dens += c * rho(r);
                    pair += c * phi(r);
                }
                embed(dens) + 0.5 * pair
            };
            let step = (cut - lo) / n as f64;
            let (mut kmin, mut emin) = (0, f64::INFINITY);
            for k in 0..=n {
                let en = energy(lo + k as f64 * step);
                if en < emin {
                    (kmin, emin) = (k, en);
                }
            }
            if kmin == 0 || kmin == n {
                continue; // no bound minimum in the scanned range
            }
            let r1 = lo + kmin as f64 * step;
            if let Some(v) = einstein(e, self.masses[e], r1, cut, &phi, &rho, &embed)
                && best.is_none_or(|b| v.period_ps < b.period_ps)
            {
                best = Some(v);
            }
        }
        best
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
        let f: Vec<f64> = (0..=n)
            .map(|m| {
                if m == 0 {
                    0.0
                } else {
                    let x = (m - 1) as f64 * d;
                    1.0 + 2.0 * x + 3.0 * x * x
                }
            })
            .collect();
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

    fn shipped(name: &str) -> Potential {
        Potential::from_file(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../md-worker/potentials").join(name)).unwrap()
    }

    #[test]
    fn the_time_step_bound_comes_from_the_copper_nearest_neighbour_vibration() {
        for name in ["Cu_u3.eam", "Cu_mishin1.eam.alloy"] {
            let pot = shipped(name);
            let v = pot.vibration().unwrap();
            // Copper: a0 = 3.615 A, neighbours at 2.556 A; Einstein frequency about 5-7 THz.
            assert!((v.nn_distance - 3.615 / 2f64.sqrt()).abs() < 0.03, "{name}: {v:?}");
            assert!(v.period_ps > 0.12 && v.period_ps < 0.3, "{name}: {v:?}");
            assert_eq!(v.mass, pot.mass(0));
            let dt = pot.max_time_step().unwrap();
            assert_eq!(dt, v.period_ps / STEPS_PER_PERIOD);
            // Every time step in use (1-5 fs) passes; 5 ps is refused.
            assert!(dt > 0.005 && dt < 5.0, "{name}: {dt}");
            // Cached: the same value again.
            assert_eq!(pot.vibration(), Some(v));
        }
        let argon = Potential::LjCut(LjCut { epsilon: 0.0104, sigma: 3.4, cutoff: 8.5, mass: 39.95 });
        let v = argon.vibration().unwrap();
        assert!(v.period_ps > 0.3 && v.period_ps < 1.5, "{v:?}");
        // The null potential (no interaction) has no vibration and so no bound.
        let null = Potential::LjCut(LjCut { epsilon: 0.0, sigma: 1.0, cutoff: 1.0, mass: 1.0 });
        assert_eq!(null.max_time_step(), None);
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
