//! A direct-MD reference and the score of a run against it (Dhakal eq. 7.12): the profile
//! of `md-worker direct --slab`, the map from a 1D scene's initial positions to the reference
//! bar's coordinate, and the scores of a run's particle snapshots. Scenes validate their
//! `[reference]` with it, runs score themselves with it, reports collect the scores; it
//! depends on none of them.

use anyhow::{Context, Result};
use serde_json::Value;
use std::path::Path;

/// A direct-MD reference (a scene's `[reference] solution = "direct-md"`, or `--reference`):
/// one stress component in slabs of the reference (unstrained) coordinate at a series of times,
/// as `md-worker direct --slab` writes it (`time_ps,slab_center_nm,sxx_gpa,...`, tension
/// positive).
///
/// The 2D form (`md-worker direct --dimension 2`: `time_ps,bin_x_nm,bin_y_nm,atoms,...`) holds
/// Eulerian x-y bins with their atom counts; it is scored in the current configuration over the
/// particles in bins holding at least [`BULK_FRACTION`] of a bulk bin's atoms ([`eq_7_12_2d`]).
/// Lines starting with `#` (the command that made the file) are skipped.
#[derive(Debug, Clone, PartialEq)]
pub struct DirectProfile {
    /// 1D: (time (s), slabs sorted by X: (X (m), stress (Pa))); empty in 2D.
    pub frames: Vec<(f64, Vec<(f64, f64)>)>,
    /// 2D: (time (s), bins); empty in 1D.
    pub bins: Vec<(f64, BinFrame)>,
}

/// The Eulerian x-y bins of a 2D direct MD at one time: square bins of side `bin` from the
/// origin, `nx` along x (x fastest), `ny` along y.
#[derive(Debug, Clone, PartialEq)]
pub struct BinFrame {
    /// Bin side (m).
    pub bin: f64,
    pub nx: usize,
    pub ny: usize,
    /// Atoms per bin.
    pub atoms: Vec<usize>,
    /// The stress component per bin (Pa).
    pub stress: Vec<f64>,
}

/// A 2D bin is scored when it holds at least this fraction of a bulk bin's atoms (the issue's
/// 80 %): free surfaces, the notch's faces and the jet's edge fall out.
pub const BULK_FRACTION: f64 = 0.8;

/// Material points closer than this to either end of the reference bar are not scored: the
/// direct MD freezes 10 A end layers as walls, the continuum has reflective walls there.
pub const REFERENCE_WALL_M: f64 = 1e-9;

/// Two times closer than this (s, 1e-3 ps) are the same snapshot (the direct CSV's times
/// carry round-off from summing 1 fs steps).
pub const TIME_TOLERANCE_S: f64 = 1e-15;

impl DirectProfile {
    /// sigma_xx of the profile in `path`.
    pub fn read(path: &Path) -> Result<DirectProfile> {
        Self::read_component(path, "sxx")
    }

    /// Stress `component` (`sxx`, `syy`, `szz`: the column `<component>_gpa`) of the profile in
    /// `path`.
    pub fn read_component(path: &Path, component: &str) -> Result<DirectProfile> {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read the direct-MD reference {}", path.display()))?;
        Self::parse_component(&text, component).with_context(|| format!("direct-MD reference {}", path.display()))
    }

    pub fn parse(text: &str) -> Result<DirectProfile> {
        Self::parse_component(text, "sxx")
    }

    pub fn parse_component(text: &str, component: &str) -> Result<DirectProfile> {
        let column = format!("{component}_gpa");
        let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
        let (_, header) = lines.next().ok_or_else(|| {
            anyhow::anyhow!("is empty; expected a header time_ps,slab_center_nm,sxx_gpa,... (`md-worker direct --slab` output)")
        })?;
        let cols: Vec<&str> = header.split(',').map(str::trim).collect();
        let col = |name: &str| {
            cols.iter().position(|c| *c == name).ok_or_else(|| {
                anyhow::anyhow!("line 1: no column `{name}` (found {}); expected `md-worker direct --slab` output", cols.join(","))
            })
        };
        if cols.contains(&"bin_x_nm") {
            return Self::parse_bins(lines, &cols, &column);
        }
        let (ct, cx, cs) = (col("time_ps")?, col("slab_center_nm")?, col(&column)?);
        let mut frames: Vec<(f64, Vec<(f64, f64)>)> = Vec::new();
        for (k, line) in lines {
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            let num = |c: usize, name: &str| -> Result<f64> {
                let v = f.get(c).ok_or_else(|| anyhow::anyhow!("line {}: missing column `{name}`", k + 1))?;
                v.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| anyhow::anyhow!("line {}: `{name}` = {v:?} is not a finite number", k + 1))
            };
            let (t, x, s) = (num(ct, "time_ps")? * 1e-12, num(cx, "slab_center_nm")? * 1e-9, num(cs, &column)? * 1e9);
            match frames.iter_mut().find(|(ft, _)| (ft - t).abs() <= TIME_TOLERANCE_S) {
                Some((_, rows)) => rows.push((x, s)),
                None => frames.push((t, vec![(x, s)])),
            }
        }
        if frames.is_empty() {
            anyhow::bail!("has a header but no rows");
        }
        for (t, rows) in &mut frames {
            rows.sort_by(|a, b| a.0.total_cmp(&b.0));
            if rows.len() < 2 || rows.windows(2).any(|w| !(w[1].0 > w[0].0)) {
                anyhow::bail!("t = {} ps: needs at least two slabs with distinct centres, found {}", *t * 1e12, rows.len());
            }
        }
        Ok(DirectProfile { frames, bins: Vec::new() })
    }

    /// The rows after the header of a 2D profile: every bin of every frame, x fastest.
    fn parse_bins<'a>(lines: impl Iterator<Item = (usize, &'a str)>, cols: &[&str], column: &str) -> Result<DirectProfile> {
        let col = |name: &str| {
            cols.iter().position(|c| *c == name).ok_or_else(|| {
                anyhow::anyhow!("line 1: no column `{name}` (found {}); expected `md-worker direct --dimension 2` output", cols.join(","))
            })
        };
        let (ct, cx, cy, ca, cs) = (col("time_ps")?, col("bin_x_nm")?, col("bin_y_nm")?, col("atoms")?, col(column)?);
        // (time, rows (x, y, atoms, stress)).
        let mut raw: Vec<(f64, Vec<(f64, f64, usize, f64)>)> = Vec::new();
        for (k, line) in lines {
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            let num = |c: usize, name: &str| -> Result<f64> {
                let v = f.get(c).ok_or_else(|| anyhow::anyhow!("line {}: missing column `{name}`", k + 1))?;
                v.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| anyhow::anyhow!("line {}: `{name}` = {v:?} is not a finite number", k + 1))
            };
            let t = num(ct, "time_ps")? * 1e-12;
            let a = num(ca, "atoms")?;
            anyhow::ensure!(a >= 0.0 && a.fract() == 0.0, "line {}: `atoms` = {a} is not a count", k + 1);
            let row = (num(cx, "bin_x_nm")? * 1e-9, num(cy, "bin_y_nm")? * 1e-9, a as usize, num(cs, column)? * 1e9);
            match raw.iter_mut().find(|(ft, _)| (ft - t).abs() <= TIME_TOLERANCE_S) {
                Some((_, rows)) => rows.push(row),
                None => raw.push((t, vec![row])),
            }
        }
        anyhow::ensure!(!raw.is_empty(), "has a header but no rows");
        let mut bins = Vec::new();
        for (t, rows) in raw {
            let ps = t * 1e12;
            let (x0, y0) = (rows[0].0, rows[0].1);
            anyhow::ensure!(
                x0 > 0.0 && (y0 - x0).abs() <= 1e-9 * x0,
                "t = {ps} ps: the first bin's centre ({x0}, {y0}) m is not (b/2, b/2) of square bins from the origin"
            );
            let bin = 2.0 * x0;
            let nx = rows.iter().take_while(|r| (r.1 - y0).abs() <= 1e-6 * bin).count();
            anyhow::ensure!(rows.len() % nx == 0, "t = {ps} ps: {} bins is not a whole number of rows of {nx}", rows.len());
            let ny = rows.len() / nx;
            for (k, r) in rows.iter().enumerate() {
                let (kx, ky) = (k % nx, k / nx);
                let want = ((kx as f64 + 0.5) * bin, (ky as f64 + 0.5) * bin);
                anyhow::ensure!(
                    (r.0 - want.0).abs() <= 1e-6 * bin && (r.1 - want.1).abs() <= 1e-6 * bin,
                    "t = {ps} ps: bin {k} has its centre at ({:e}, {:e}) m, expected ({:e}, {:e}) (x fastest, side {bin:e} m from the origin)",
                    r.0,
                    r.1,
                    want.0,
                    want.1
                );
            }
            let frame = BinFrame { bin, nx, ny, atoms: rows.iter().map(|r| r.2).collect(), stress: rows.iter().map(|r| r.3).collect() };
            bins.push((t, frame));
        }
        Ok(DirectProfile { frames: Vec::new(), bins })
    }

    /// Whether this is a 2D (Eulerian bin) profile.
    pub fn is_2d(&self) -> bool {
        !self.bins.is_empty()
    }

    /// Atoms of a bulk bin: the most common count among the occupied bins of the first frame
    /// (the undeformed sample; ties to the larger count). 0 for a 1D profile.
    pub fn bulk_atoms(&self) -> usize {
        let Some((_, f)) = self.bins.iter().min_by(|a, b| a.0.total_cmp(&b.0)) else { return 0 };
        let mut counts: std::collections::BTreeMap<usize, usize> = std::collections::BTreeMap::new();
        for &a in f.atoms.iter().filter(|a| **a > 0) {
            *counts.entry(a).or_default() += 1;
        }
        counts.iter().max_by(|a, b| a.1.cmp(b.1).then(a.0.cmp(b.0))).map_or(0, |(a, _)| *a)
    }

    /// The 2D bins at time `t` (s), if the reference has that time.
    pub fn bins_at(&self, t: f64) -> Option<&BinFrame> {
        self.bins
            .iter()
            .filter(|(ft, _)| (ft - t).abs() <= TIME_TOLERANCE_S)
            .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
            .map(|(_, f)| f)
    }

    fn times(&self) -> Vec<f64> {
        self.frames.iter().map(|f| f.0).chain(self.bins.iter().map(|f| f.0)).collect()
    }

    /// The slabs at time `t` (s), if the reference has that time.
    pub fn at(&self, t: f64) -> Option<&[(f64, f64)]> {
        self.frames
            .iter()
            .filter(|(ft, _)| (ft - t).abs() <= TIME_TOLERANCE_S)
            .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
            .map(|(_, r)| r.as_slice())
    }

    /// Whether the profile (1D or 2D) has a frame at `t` (s).
    pub fn has_frame(&self, t: f64) -> bool {
        self.at(t).is_some() || self.bins_at(t).is_some()
    }

    /// First and last time of the profile (s).
    pub fn time_range(&self) -> (f64, f64) {
        let t = self.times();
        (t.iter().copied().fold(f64::INFINITY, f64::min), t.iter().copied().fold(f64::NEG_INFINITY, f64::max))
    }

    /// The profile's times (ps), for messages.
    pub fn times_ps(&self) -> String {
        self.times().iter().map(|t| format!("{}", (t * 1e15).round() / 1e3)).collect::<Vec<_>>().join(", ")
    }
}

/// sigma_xx of slabs (X, s) sorted by X, linear in X between slab centres, constant beyond.
pub fn interpolate(rows: &[(f64, f64)], x: f64) -> f64 {
    let i = rows.partition_point(|r| r.0 < x);
    if i == 0 {
        return rows[0].1;
    }
    if i == rows.len() {
        return rows[rows.len() - 1].1;
    }
    let ((x0, y0), (x1, y1)) = (rows[i - 1], rows[i]);
    y0 + (y1 - y0) * (x - x0) / (x1 - x0)
}

/// The seed's eq. 7.12 over (s_MD, s_MS) pairs of one stress component (Pa):
/// eps = sqrt(sum (s_MD - s_MS)^2 / sum s_MD^2). Returns (eps, pairs). Every form of the score
/// (the 1D slabs of [`eq_7_12`]; a 2D form would sample bins) ends here.
pub fn eq_7_12_sum(pairs: impl IntoIterator<Item = (f64, f64)>) -> Result<(f64, usize)> {
    let (mut num, mut den, mut count) = (0.0, 0.0, 0);
    for (r, s) in pairs {
        num += (r - s) * (r - s);
        den += r * r;
        count += 1;
    }
    if count == 0 {
        anyhow::bail!("no material point to score");
    }
    if den == 0.0 {
        anyhow::bail!("the reference stress is zero at every scored point: eq. 7.12 is undefined");
    }
    let eps = (num / den).sqrt();
    anyhow::ensure!(eps.is_finite(), "eq. 7.12 is not finite (a run's stress is not finite)");
    Ok((eps, count))
}

/// The seed's eq. 7.12 in 1D: eps = sqrt(sum (s_MD - s_MS)^2 / sum s_MD^2) over the material
/// points `(X, s_MS)` (reference coordinate (m), stress (Pa)), with s_MD the reference slabs
/// interpolated at X. Points within `wall` of the reference bar's ends (the outer slab faces)
/// are left out. Returns (eps, points scored).
pub fn eq_7_12(reference: &[(f64, f64)], points: &[(f64, f64)], wall: f64) -> Result<(f64, usize)> {
    let n = reference.len();
    let lo = reference[0].0 - 0.5 * (reference[1].0 - reference[0].0);
    let hi = reference[n - 1].0 + 0.5 * (reference[n - 1].0 - reference[n - 2].0);
    let pairs: Vec<(f64, f64)> =
        points.iter().filter(|&&(x, _)| x >= lo + wall && x <= hi - wall).map(|&(x, s)| (interpolate(reference, x), s)).collect();
    if pairs.is_empty() {
        anyhow::bail!(
            "no material point lies inside the reference bar ({:.4} to {:.4} nm, less {} nm at each end)",
            lo * 1e9,
            hi * 1e9,
            wall * 1e9
        );
    }
    eq_7_12_sum(pairs)
}

/// The seed's eq. 7.12 in 2D: over the particles `(x, y, s_MS)` (current position (m), stress
/// (Pa)) that lie in a bin of `frame` holding at least `min_atoms` atoms, s_MD that bin's
/// stress (the bins are the reference's own Eulerian resolution: no interpolation). x is taken
/// periodic over the bins' width. Returns (eps, points scored, points left out).
pub fn eq_7_12_2d(frame: &BinFrame, points: &[(f64, f64, f64)], min_atoms: f64) -> Result<(f64, usize, usize)> {
    let width = frame.nx as f64 * frame.bin;
    let bin_of = |x: f64, y: f64| -> Option<usize> {
        let (fx, fy) = (x.rem_euclid(width) / frame.bin, y / frame.bin);
        if !(fy >= 0.0 && fy < frame.ny as f64 && fx.is_finite()) {
            return None;
        }
        Some((fy.floor() as usize) * frame.nx + (fx.floor() as usize).min(frame.nx - 1))
    };
    let pairs: Vec<(f64, f64)> = points
        .iter()
        .filter_map(|&(x, y, s)| bin_of(x, y).filter(|&k| frame.atoms[k] as f64 >= min_atoms).map(|k| (frame.stress[k], s)))
        .collect();
    let left_out = points.len() - pairs.len();
    if pairs.is_empty() {
        anyhow::bail!("no particle lies in a bin of the reference holding at least {min_atoms} atoms ({} particles)", points.len());
    }
    let (eps, n) = eq_7_12_sum(pairs)?;
    Ok((eps, n, left_out))
}

/// One eq. 7.12 score of a run: at `time` (s), from the snapshot nearest to it.
#[derive(Debug, Clone, PartialEq)]
pub struct Score {
    pub time: f64,
    pub snapshot_step: u64,
    pub snapshot_time: f64,
    pub error: f64,
    pub points: usize,
    /// Material points not scored (1D: within the walls; 2D: outside the bulk-like bins).
    pub excluded: usize,
}

/// The eq. 7.12 error of `component` of the run in `run_dir` against `profile` at each of
/// `times` (s), each from the snapshot of `snapshots/index.csv` nearest to it (scored against
/// the profile's frame at the time asked for). The one implementation of the score: `mscale
/// run` calls it for a scene's `[reference] solution = "direct-md"`, `mscale report` reads it
/// back from the runs' summary.json.
///
/// A 2D profile scores the particles by their current (x, y) ([`eq_7_12_2d`]) and needs no
/// `map`; a 1D one maps x0 with `map` (required).
pub fn score_run(
    profile: &DirectProfile,
    component: &str,
    times: &[f64],
    map: Option<&ReferenceMap>,
    run_dir: &Path,
) -> Result<Vec<Score>> {
    let index_path = run_dir.join("snapshots/index.csv");
    let index = std::fs::read_to_string(&index_path).with_context(|| format!("cannot read {}", index_path.display()))?;
    let snaps: Vec<(u64, f64, String)> = index
        .lines()
        .skip(1)
        .filter_map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            Some((f.first()?.parse().ok()?, f.get(1)?.parse().ok()?, f.get(2)?.to_string()))
        })
        .collect();
    let mut out = Vec::new();
    for &t in times {
        let Some((step, ts, file)) = snaps.iter().min_by(|a, b| (a.1 - t).abs().total_cmp(&(b.1 - t).abs())) else {
            anyhow::bail!("{} lists no snapshot", index_path.display());
        };
        let path = run_dir.join("snapshots").join(file);
        if profile.is_2d() {
            let frame = profile.bins_at(t).ok_or_else(|| {
                anyhow::anyhow!("the direct-MD reference has no frame at t = {} ps (it has {} ps)", t * 1e12, profile.times_ps())
            })?;
            let points = read_columns(&path, &["x", "y", component])?;
            let pts: Vec<(f64, f64, f64)> = points.iter().map(|p| (p[0], p[1], p[2])).collect();
            let min_atoms = BULK_FRACTION * profile.bulk_atoms() as f64;
            let (error, n, excluded) = eq_7_12_2d(frame, &pts, min_atoms)
                .with_context(|| format!("eq. 7.12 of {component} of {} at t = {} ps", path.display(), t * 1e12))?;
            out.push(Score { time: t, snapshot_step: *step, snapshot_time: *ts, error, points: n, excluded });
            continue;
        }
        let map = map.ok_or_else(|| anyhow::anyhow!("a 1D direct-MD reference needs the map of the scene's bodies"))?;
        let points = read_x0_component(&path, component)?;
        let pts: Vec<(f64, f64)> = points.iter().map(|&(x0, s)| (map.x_ref(x0), s)).collect();
        let reference = profile.at(t).ok_or_else(|| {
            anyhow::anyhow!("the direct-MD reference has no frame at t = {} ps (it has {} ps)", t * 1e12, profile.times_ps())
        })?;
        let (error, n) = eq_7_12(reference, &pts, REFERENCE_WALL_M)
            .with_context(|| format!("eq. 7.12 of {component} of {} at t = {} ps", path.display(), t * 1e12))?;
        out.push(Score { time: t, snapshot_step: *step, snapshot_time: *ts, error, points: n, excluded: pts.len() - n });
    }
    Ok(out)
}

/// The summary.json `errors` of a run scored against a direct-MD reference: the eq. 7.12 error
/// per time (with the snapshot it came from), and a flat `<component>_error_<t>ps` per time
/// (the report's column names).
pub fn direct_md_errors_json(profile: &Path, component: &str, scores: &[Score], two_d: bool) -> Value {
    let mut m = serde_json::Map::new();
    m.insert("reference".into(), "direct-md".into());
    m.insert("profile".into(), profile.display().to_string().into());
    m.insert("component".into(), component.into());
    let measure = if two_d {
        "eq. 7.12: sqrt(sum (s_MD - s_MS)^2 / sum s_MD^2) over the particles at their current (x, y), s_MD the stress of the direct MD's Eulerian bin holding the particle, bins with fewer than 80 % of a bulk bin's atoms (free surfaces, the jet's edge) left out (`excluded`)"
    } else {
        "eq. 7.12: sqrt(sum (s_MD - s_MS)^2 / sum s_MD^2) over the material points in the reference coordinate, points within 1 nm of the bar's ends left out"
    };
    m.insert("measure".into(), measure.into());
    m.insert(
        "times".into(),
        scores
            .iter()
            .map(|s| serde_json::json!({"time_ps": ps(s.time), "snapshot_step": s.snapshot_step, "snapshot_time_ps": ps(s.snapshot_time), "error": s.error, "points": s.points, "excluded": s.excluded}))
            .collect::<Vec<_>>()
            .into(),
    );
    for s in scores {
        m.insert(error_column(component, s.time), s.error.into());
    }
    Value::Object(m)
}

/// A time (s) in ps, rounded to 1e-6 ps (the round-off of summed steps removed).
/// The summary and report column of `component`'s error at `t` (s): `sxx_error_5ps`.
pub(crate) fn error_column(component: &str, t: f64) -> String {
    format!("{component}_error_{}ps", (t * 1e15).round() / 1e3)
}

fn ps(t: f64) -> f64 {
    (t * 1e18).round() / 1e6
}

/// The log line of a scored run: `eq. 7.12 error of sxx against direct MD: 4.58 % at 5 ps, ...`.
pub fn direct_md_log_line(component: &str, scores: &[Score]) -> String {
    let parts: Vec<String> = scores
        .iter()
        .map(|s| {
            let at = if (s.snapshot_time - s.time).abs() > TIME_TOLERANCE_S {
                format!(" (snapshot at {} ps)", ps(s.snapshot_time))
            } else {
                String::new()
            };
            format!("{:.2} % at {} ps{at}", 100.0 * s.error, ps(s.time))
        })
        .collect();
    let (n, ex) = scores.first().map_or((0, 0), |s| (s.points, s.excluded));
    format!("eq. 7.12 error of {component} against direct MD: {} ({n} points, {ex} left out)", parts.join(", "))
}

/// The scores a run wrote into its summary.json `errors`, one per time of `times` (s) in order;
/// empty unless the run scored every one of them.
pub fn scores_of_summary(summary: &Value, times: &[f64]) -> Vec<(f64, usize)> {
    let Some(list) = summary["errors"]["times"].as_array() else { return Vec::new() };
    let found: Option<Vec<(f64, usize)>> = times
        .iter()
        .map(|&t| {
            let e = list.iter().find(|e| e["time_ps"].as_f64().is_some_and(|x| (x * 1e-12 - t).abs() <= TIME_TOLERANCE_S))?;
            Some((e["error"].as_f64()?, e["points"].as_u64()? as usize))
        })
        .collect();
    found.unwrap_or_default()
}

/// Maps a 1D scene's initial positions x0 (the strained configuration the bodies are given in)
/// to the reference coordinate X of an unstrained bar: bodies in order along x, each stretched
/// back by 1 / (1 + initial_strain_x), gaps between bodies kept. X starts at the first body's
/// min.
#[derive(Debug, Clone, PartialEq)]
pub struct ReferenceMap {
    /// (x0 min, x0 max, X at x0 min, 1 + strain) per body, sorted by x0.
    pub(crate) bodies: Vec<(f64, f64, f64, f64)>,
}

impl ReferenceMap {
    /// The map of a 1D scene `name` whose bodies span x0 in [lo, hi) with stretch 1 + strain_x,
    /// given as (lo, hi, stretch).
    pub fn from_bodies(name: &str, mut b: Vec<(f64, f64, f64)>) -> Result<ReferenceMap> {
        b.sort_by(|p, q| p.0.total_cmp(&q.0));
        let mut bodies = Vec::new();
        let mut prev: Option<(f64, f64)> = None; // (x0 max, X max) of the body before
        for (lo, hi, stretch) in b {
            let start = match prev {
                None => lo,
                Some((pmax, _)) if lo < pmax - 1e-9 * (hi - lo) => {
                    anyhow::bail!("bodies of scene `{name}` overlap along x at {lo:e} m: cannot map them to one reference bar")
                }
                Some((pmax, pxmax)) => pxmax + (lo - pmax).max(0.0),
            };
            bodies.push((lo, hi, start, stretch));
            prev = Some((hi, start + (hi - lo) / stretch));
        }
        Ok(ReferenceMap { bodies })
    }

    /// X of a point that starts at x0 (the body whose [min, max) holds it; the last body takes
    /// its max too).
    pub fn x_ref(&self, x0: f64) -> f64 {
        let k = self.bodies.iter().rposition(|b| x0 >= b.0).unwrap_or(0);
        let (lo, _, start, stretch) = self.bodies[k];
        start + (x0 - lo) / stretch
    }
}

/// The `names` columns of every material point in a particle CSV.
fn read_columns(path: &Path, names: &[&str]) -> Result<Vec<Vec<f64>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut lines = text.lines();
    let cols: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let idx: Vec<usize> = names
        .iter()
        .map(|n| cols.iter().position(|c| c == n).ok_or_else(|| anyhow::anyhow!("{}: no column `{n}`", path.display())))
        .collect::<Result<_>>()?;
    lines
        .enumerate()
        .map(|(k, l)| {
            let f: Vec<&str> = l.split(',').collect();
            idx.iter()
                .map(|&c| {
                    f.get(c)
                        .and_then(|v| v.parse::<f64>().ok())
                        .ok_or_else(|| anyhow::anyhow!("{} line {}: unreadable {}", path.display(), k + 2, names.join(" or ")))
                })
                .collect()
        })
        .collect()
}

/// (x0, stress `component`) of every material point in a particle CSV.
fn read_x0_component(path: &Path, component: &str) -> Result<Vec<(f64, f64)>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut lines = text.lines();
    let cols: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    let col = |n: &str| cols.iter().position(|c| *c == n).ok_or_else(|| anyhow::anyhow!("{}: no column `{n}`", path.display()));
    let (cx, cs) = (col("x0")?, col(component)?);
    lines
        .enumerate()
        .map(|(k, l)| {
            let f: Vec<&str> = l.split(',').collect();
            let get = |c: usize| {
                f.get(c)
                    .and_then(|v| v.parse::<f64>().ok())
                    .ok_or_else(|| anyhow::anyhow!("{} line {}: unreadable x0 or {component}", path.display(), k + 2))
            };
            Ok((get(cx)?, get(cs)?))
        })
        .collect()
}

/// The error of a lithiated thin film (`[reference] solution = "thin-film-lithiation"`)
/// against its derived in-plane stress path ([`continuum::exact::thin_film_stress`]), observed
/// after every step: at each point of the film, the in-plane stress sigma_yy (= sigma_zz in 1D)
/// against the exact stress at the point's concentration change, over sigma_Y; the plastic
/// strain likewise; and the normal stress |sigma_xx| / sigma_Y, which the exact path takes as
/// zero (the quasi-static check of the dynamic run).
#[derive(Debug, Clone, PartialEq)]
pub struct ThinFilmError {
    law: continuum::silicon::ChemoPlastic,
    /// Global point ids of the film.
    points: std::ops::Range<usize>,
    /// Initial concentration of the film.
    c0: f64,
    steps: u64,
    max_stress_error: f64,
    max_at_dc: f64,
    max_plastic_strain_error: f64,
    max_normal_stress: f64,
    final_dc: f64,
    final_stress: f64,
    final_exact: f64,
    final_stress_error: f64,
}

impl ThinFilmError {
    pub fn new(law: continuum::silicon::ChemoPlastic, points: std::ops::Range<usize>, c0: f64) -> Self {
        ThinFilmError {
            law,
            points,
            c0,
            steps: 0,
            max_stress_error: 0.0,
            max_at_dc: 0.0,
            max_plastic_strain_error: 0.0,
            max_normal_stress: 0.0,
            final_dc: 0.0,
            final_stress: 0.0,
            final_exact: 0.0,
            final_stress_error: 0.0,
        }
    }

    /// Scores the state after a step. Non-finite values count as an infinite error.
    pub fn observe<const D: usize>(&mut self, sim: &continuum::Simulation<D>) {
        let pts = &sim.points;
        let sy = self.law.yield_stress;
        let (mut worst, mut at, mut sum_s, mut sum_e, mut sum_dc, mut n) = (0.0f64, 0.0, 0.0, 0.0, 0.0, 0usize);
        for p in self.points.clone() {
            let dc = pts.scalar.get(p).copied().unwrap_or(self.c0) - self.c0;
            let (exact, eps) = continuum::exact::thin_film_stress(&self.law, dc);
            let s = pts.stress[p][1][1];
            let e = ((s - exact) / sy).abs();
            let e = if e.is_finite() { e } else { f64::INFINITY };
            if e > worst || n == 0 {
                (worst, at) = (e, dc);
            }
            let ep = pts.plastic_strain.get(p).copied().unwrap_or(0.0);
            let ee = (ep - eps).abs();
            self.max_plastic_strain_error = self.max_plastic_strain_error.max(if ee.is_finite() { ee } else { f64::INFINITY });
            let normal = (pts.stress[p][0][0] / sy).abs();
            self.max_normal_stress = self.max_normal_stress.max(if normal.is_finite() { normal } else { f64::INFINITY });
            (sum_s, sum_e, sum_dc, n) = (sum_s + s, sum_e + exact, sum_dc + dc, n + 1);
        }
        if worst > self.max_stress_error || self.steps == 0 {
            (self.max_stress_error, self.max_at_dc) = (worst, at);
        }
        let k = n.max(1) as f64;
        (self.final_dc, self.final_stress, self.final_exact, self.final_stress_error) = (sum_dc / k, sum_s / k, sum_e / k, worst);
        self.steps += 1;
    }

    /// summary.json `errors`.
    pub fn json(&self) -> Value {
        let num = |v: f64| if v.is_finite() { serde_json::json!(v) } else { Value::Null };
        serde_json::json!({
            "reference": "thin-film-lithiation",
            "measure": "max over the film's points and the steps of |sigma_yy - sigma_exact(dc)| / sigma_Y, sigma_exact the derived in-plane stress path of a film on a rigid substrate (continuum::exact::thin_film_stress)",
            "steps_scored": self.steps,
            "stress_error_max": num(self.max_stress_error),
            "stress_error_max_at_dc": num(self.max_at_dc),
            "stress_error_final": num(self.final_stress_error),
            "plastic_strain_error_max": num(self.max_plastic_strain_error),
            "normal_stress_max_over_yield": num(self.max_normal_stress),
            "final_dc": num(self.final_dc),
            "final_in_plane_stress_pa": num(self.final_stress),
            "final_exact_stress_pa": num(self.final_exact),
            "biaxial_modulus_pa": self.law.biaxial_modulus(),
            "yield_dc": self.law.yield_stress / (self.law.biaxial_modulus() * self.law.chemical_expansion),
        })
    }

    /// The run's log line.
    pub fn log_line(&self) -> String {
        format!(
            "thin-film error: in-plane stress {:.3e} sigma_Y at worst (dc = {:.4}), {:.3e} at the end (dc = {:.4}: {:.4e} Pa, exact {:.4e} Pa); |sigma_xx| <= {:.2e} sigma_Y",
            self.max_stress_error,
            self.max_at_dc,
            self.final_stress_error,
            self.final_dc,
            self.final_stress,
            self.final_exact,
            self.max_normal_stress
        )
    }
}

/// The quasi-static check of a density-scaled (or lithiated) run (summary.json
/// `quasi_static`): the kinetic energy of the points against their elastic energy
/// sum_p V_p (p^2 / (2 K) + s:s / (4 G)) (isotropic, from the stress: K, G per body), and the
/// acoustic transit time of the largest body at the scaled density against the process time.
#[derive(Debug, Clone)]
pub struct QuasiStatic {
    pub density_scaling: f64,
    /// (K, G) per body index (None: a law with no elastic energy of this form; skipped).
    pub moduli: Vec<Option<(f64, f64)>>,
    /// Acoustic transit time of the largest body at the scaled density (s).
    pub transit_s: f64,
    /// The time of the process the run follows (s): the lithiation's run time, or L^2 / D.
    pub process_s: f64,
    /// Steps before this time are not scored (the start-up transient: 10 transits).
    pub score_after_s: f64,
    max_ratio: f64,
    max_ratio_at: f64,
    final_ratio: f64,
    max_kinetic: f64,
    final_elastic: f64,
}

impl QuasiStatic {
    pub fn new(density_scaling: f64, moduli: Vec<Option<(f64, f64)>>, transit_s: f64, process_s: f64) -> Self {
        QuasiStatic {
            density_scaling,
            moduli,
            transit_s,
            process_s,
            score_after_s: 10.0 * transit_s,
            max_ratio: 0.0,
            max_ratio_at: f64::NAN,
            final_ratio: f64::NAN,
            max_kinetic: 0.0,
            final_elastic: 0.0,
        }
    }

    /// Scores the state after a step.
    pub fn observe<const D: usize>(&mut self, sim: &continuum::Simulation<D>) {
        let pts = &sim.points;
        let (mut kinetic, mut elastic) = (0.0, 0.0);
        for p in 0..pts.len() {
            let Some(Some((k, g))) = self.moduli.get(pts.body[p] as usize) else { continue };
            kinetic += 0.5 * pts.mass[p] * pts.v[p].iter().map(|v| v * v).sum::<f64>();
            let s = &pts.stress[p];
            let pr = -(s[0][0] + s[1][1] + s[2][2]) / 3.0;
            let mut dev2 = 0.0;
            for (i, row) in s.iter().enumerate() {
                for (j, v) in row.iter().enumerate() {
                    let d = v + if i == j { pr } else { 0.0 };
                    dev2 += d * d;
                }
            }
            elastic += pts.volume[p] * (pr * pr / (2.0 * k) + dev2 / (4.0 * g));
        }
        let ratio = if elastic > 0.0 { kinetic / elastic } else { f64::INFINITY };
        self.max_kinetic = self.max_kinetic.max(kinetic);
        self.final_elastic = elastic;
        self.final_ratio = ratio;
        if sim.time >= self.score_after_s && (ratio > self.max_ratio || self.max_ratio_at.is_nan()) {
            (self.max_ratio, self.max_ratio_at) = (ratio, sim.time);
        }
    }

    /// summary.json `quasi_static`.
    pub fn json(&self) -> Value {
        let num = |v: f64| if v.is_finite() { serde_json::json!(v) } else { Value::Null };
        serde_json::json!({
            "density_scaling": self.density_scaling,
            "measure": "kinetic / elastic energy of the points (elastic = sum V (p^2/(2K) + s:s/(4G))), max over the steps after 10 acoustic transits (after the lithiation ramp and 10 transits with a ramp)",
            "scored_after_s": num(self.score_after_s),
            "max_kinetic_over_elastic": num(self.max_ratio),
            "max_at_s": num(self.max_ratio_at),
            "final_kinetic_over_elastic": num(self.final_ratio),
            "final_elastic_energy_j": num(self.final_elastic),
            "max_kinetic_energy_j": num(self.max_kinetic),
            "acoustic_transit_s": num(self.transit_s),
            "process_time_s": num(self.process_s),
            "transit_over_process_time": num(self.transit_s / self.process_s),
            "quasi_static": self.max_ratio < 1e-3 && self.transit_s < 1e-2 * self.process_s,
        })
    }
}
