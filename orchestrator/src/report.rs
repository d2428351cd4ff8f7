//! `mscale report error-vs-time`: run every combination of parameter sweeps of one scene and
//! tabulate error against cost, the question users ask before trusting a setting.
//!
//! Without `--reference` the error is the scene's own `[reference]`: an exact solution, or a
//! direct-MD profile (`solution = "direct-md"`). With `--reference CSV --reference-times 5,10`
//! every run is given that direct-MD profile (`md-worker direct --slab`) as its reference, and
//! writes snapshots exactly at those times (which must be whole continuum steps). A run with a
//! direct-MD reference scores itself by the seed's eq. 7.12,
//! eps = sqrt(sum (s_MD - s_MS)^2 / sum s_MD^2), of one stress component (sigma_xx along the
//! bar) over the material points in the reference coordinate (the bodies' initial strain undone,
//! see [`ReferenceMap`]), in [`score_run`]: `mscale run` writes it into summary.json, the report
//! reads it from there. 1D only: the 2D form is not implemented yet.

use crate::output;
use crate::run::{self, Outcome, RunOptions};
use crate::scene::{self, SceneError};
use anyhow::{Context, Result};
use serde_json::Value;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// One `--sweep key=v1,v2,...`.
#[derive(Debug, Clone, PartialEq)]
pub struct Sweep {
    pub key: String,
    pub values: Vec<String>,
}

impl std::str::FromStr for Sweep {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let (key, values) = s.split_once('=').ok_or_else(|| format!("expected --sweep key=v1,v2,..., got `{s}`"))?;
        let values: Vec<String> = values.split(',').map(|v| v.trim().to_string()).filter(|v| !v.is_empty()).collect();
        if key.split('+').any(|k| k.trim().is_empty()) || values.is_empty() {
            return Err(format!("expected --sweep key=v1,v2,..., got `{s}`"));
        }
        Ok(Sweep { key: key.trim().to_string(), values })
    }
}

/// Every combination of the sweeps' values, one value per sweep (first sweep slowest).
pub fn value_combinations(sweeps: &[Sweep]) -> Vec<Vec<String>> {
    let mut out = vec![Vec::new()];
    for s in sweeps {
        out = out
            .into_iter()
            .flat_map(|prefix| {
                s.values.iter().map(move |v| {
                    let mut c = prefix.clone();
                    c.push(v.clone());
                    c
                })
            })
            .collect();
    }
    out
}

/// Every combination of the sweeps, as lists of `key=value` overrides (first sweep slowest). A
/// key `a+b` sets every one of its keys to the value (`--sweep
/// bodies.left.material.seed+bodies.right.material.seed=1,2`).
pub fn combinations(sweeps: &[Sweep]) -> Vec<Vec<String>> {
    value_combinations(sweeps)
        .into_iter()
        .map(|values| sweeps.iter().zip(&values).flat_map(|(s, v)| s.key.split('+').map(move |k| format!("{}={v}", k.trim()))).collect())
        .collect()
}

/// Overrides applied to every run of a report: only the final state is written, so the time
/// measured is the solver's, not the output's.
const REPORT_OUTPUT: [&str; 4] = ["output.snapshots=1", "output.vtk=false", "output.plots=false", "output.particles=true"];

/// One finished run of a report.
pub struct Row {
    pub values: Vec<String>,
    pub summary: Value,
    /// MD atom-steps of the run (0 without md bodies).
    pub atom_steps: f64,
    /// eq. 7.12 error and points scored at each time of the direct-MD reference (empty without
    /// one, or when the run did not complete).
    pub scores: Vec<(f64, usize)>,
}

/// Validates every combination first (a bad value is refused before anything runs), then runs
/// them one after another and writes `report.csv` and `report.png` in `out`. With a
/// `reference` (`--reference`), every run is given it as its scene's `[reference] solution =
/// "direct-md"` and writes snapshots at the reference times; without one, a scene's own
/// direct-md reference is used. Either way each run scores itself ([`score_run`]) and the
/// report reads the errors from its summary.json.
///
/// `replicas` names one of the sweeps (typically the MD seeds, `a.seed+b.seed=1,2,3`) whose
/// runs are replicas of one setting: `replicas.csv` then gives, per combination of the other
/// sweeps, the mean and sample standard deviation over them.
pub fn error_vs_time(
    scene_path: &Path,
    sets: &[String],
    sweeps: &[Sweep],
    out: &Path,
    workers: &[String],
    reference: Option<&ReferenceSpec>,
    replicas: Option<&str>,
) -> Result<Vec<Row>, ReportError> {
    let replica_sweep = match replicas {
        None => None,
        Some(key) => Some(sweeps.iter().position(|s| s.key == key).ok_or_else(|| {
            ReportError::Input(format!(
                "--replicas {key}: no --sweep has this key (sweeps: {}); give the replica sweep's key exactly",
                sweeps.iter().map(|s| s.key.as_str()).collect::<Vec<_>>().join(", ")
            ))
        })?),
    };
    let combos = combinations(sweeps);
    let value_rows = value_combinations(sweeps);
    let mut loaded = Vec::new();
    for combo in &combos {
        let mut all: Vec<String> =
            sets.iter().cloned().chain(REPORT_OUTPUT.iter().map(|s| s.to_string())).chain(combo.iter().cloned()).collect();
        if let Some(r) = reference {
            let own = scene::load(scene_path, &all).map_err(ReportError::Scene)?;
            if let Some(scene::Reference::IsothermalRiemann(_)) = own.scene.reference {
                return Err(ReportError::Input(format!(
                    "--reference: scene `{}` names an isothermal-riemann reference; a direct-MD reference scores the stress of md or elastic bars",
                    own.scene.name
                )));
            }
            all.extend(r.overrides());
            let l = scene::load(scene_path, &all).map_err(ReportError::Scene)?;
            let bad = |e: anyhow::Error| ReportError::Input(format!("{e:#} (run {})", combo.join(" ")));
            let snapshots = r.snapshots(&l).map_err(bad)?;
            all.push(format!("output.snapshots={snapshots}"));
        }
        let l = scene::load(scene_path, &all).map_err(ReportError::Scene)?;
        let atom_steps = md_atom_steps(&l).map_err(|e| ReportError::Input(format!("{e:#}")))?;
        loaded.push((l, atom_steps));
    }
    // The times and component scored (the columns): those of the reference every run has.
    let (times, component) = match loaded.first().and_then(|(l, _)| l.scene.reference.as_ref()) {
        Some(scene::Reference::DirectMd(r)) => (r.times_ps.iter().map(|t| t * 1e-12).collect::<Vec<f64>>(), r.component.clone()),
        _ => (Vec::new(), "sxx".to_string()),
    };
    let mut rows = Vec::new();
    for (k, (combo, (l, atom_steps))) in combos.iter().zip(&loaded).enumerate() {
        tracing::info!("report run {}/{}: {}", k + 1, combos.len(), combo.join(" "));
        let dir = out.join("runs").join(format!("{k:03}"));
        let mut opts = RunOptions::new(dir.clone(), std::env::args().collect());
        opts.progress_bar = false;
        opts.workers = workers.to_vec();
        let summary = match run::run(l, &opts).map_err(ReportError::Io)? {
            Outcome::Completed(s) | Outcome::Failed(s, _) => s,
            Outcome::Cancelled { step, .. } => return Err(ReportError::Io(anyhow::anyhow!("report run {k} was cancelled at step {step}"))),
        };
        let scores = if summary["status"] == "completed" { scores_of_summary(&summary, &times) } else { Vec::new() };
        if summary["status"] == "completed" && !times.is_empty() && scores.is_empty() {
            return Err(ReportError::Io(anyhow::anyhow!(
                "report run {} was not scored against its direct-MD reference: {}",
                k + 1,
                summary["errors"]["failure"].as_str().unwrap_or("no errors in its summary.json")
            )));
        }
        for (t, (e, n)) in times.iter().zip(&scores) {
            tracing::info!("report run {}: eq. 7.12 error of {component} at {} ps = {:.2} % over {n} points", k + 1, t * 1e12, 100.0 * e);
        }
        rows.push(Row { values: value_rows[k].clone(), summary, atom_steps: *atom_steps, scores });
        write_outputs(sweeps, &rows, out, &times, &component).map_err(ReportError::Io)?;
        if let Some(r) = replica_sweep {
            let text = replica_summary_of(&component, sweeps, r, &rows, &times);
            output::write_atomic(&out.join("replicas.csv"), text.as_bytes()).map_err(ReportError::Io)?;
        }
    }
    Ok(rows)
}

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{0}")]
    Scene(SceneError),
    /// `--reference` or `--replicas` does not fit the scene or the sweeps (refused before
    /// anything runs).
    #[error("{0}")]
    Input(String),
    #[error("{0:#}")]
    Io(anyhow::Error),
}

fn field(s: &Value, path: &[&str]) -> String {
    let mut v = s;
    for p in path {
        v = &v[*p];
    }
    match v {
        Value::Null => String::new(),
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// Mean and sample standard deviation (empty below two values).
fn mean_std(v: &[f64]) -> (f64, Option<f64>) {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let std = (v.len() > 1).then(|| (v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1.0)).sqrt());
    (mean, std)
}

/// `replicas.csv`: per combination of the sweeps other than `replica`, the number of completed
/// replicas and the mean and sample standard deviation of wall time and of each error.
pub fn replica_summary(sweeps: &[Sweep], replica: usize, rows: &[Row], times: &[f64]) -> String {
    replica_summary_of("sxx", sweeps, replica, rows, times)
}

/// [`replica_summary`] of the errors of a stress `component`.
fn replica_summary_of(component: &str, sweeps: &[Sweep], replica: usize, rows: &[Row], times: &[f64]) -> String {
    let mut csv = String::new();
    for (k, s) in sweeps.iter().enumerate() {
        if k != replica {
            let _ = write!(csv, "{},", s.key);
        }
    }
    csv.push_str("replicas,wall_seconds_mean,wall_seconds_std");
    for &t in times {
        let c = error_column(component, t);
        let _ = write!(csv, ",{c}_mean,{c}_std");
    }
    csv.push('\n');
    let key = |r: &Row| r.values.iter().enumerate().filter(|(k, _)| *k != replica).map(|(_, v)| v.clone()).collect::<Vec<_>>();
    let mut groups: Vec<(Vec<String>, Vec<&Row>)> = Vec::new();
    for r in rows.iter().filter(|r| r.summary["status"] == "completed") {
        let k = key(r);
        match groups.iter_mut().find(|(g, _)| *g == k) {
            Some((_, members)) => members.push(r),
            None => groups.push((k, vec![r])),
        }
    }
    let cell = |(m, s): (f64, Option<f64>)| format!("{m:e},{}", s.map(|s| format!("{s:e}")).unwrap_or_default());
    for (values, members) in groups {
        for v in &values {
            let _ = write!(csv, "{},", v.replace(',', ";"));
        }
        let wall: Vec<f64> = members.iter().filter_map(|r| r.summary["wall_seconds"].as_f64()).collect();
        let _ = write!(csv, "{},{}", members.len(), cell(mean_std(&wall)));
        for k in 0..times.len() {
            let e: Vec<f64> = members.iter().filter_map(|r| r.scores.get(k).map(|s| s.0)).collect();
            let _ = write!(csv, ",{}", if e.is_empty() { ",".to_string() } else { cell(mean_std(&e)) });
        }
        csv.push('\n');
    }
    csv
}

/// Column name of the eq. 7.12 error of `component` at time `t` (s): `sxx_error_5ps`.
fn error_column(component: &str, t: f64) -> String {
    format!("{component}_error_{}ps", (t * 1e15).round() / 1e3)
}

fn write_outputs(sweeps: &[Sweep], rows: &[Row], out: &Path, times: &[f64], component: &str) -> Result<()> {
    let mut csv = String::new();
    for s in sweeps {
        let _ = write!(csv, "{},", s.key);
    }
    csv.push_str("method,status,pressure_l1,pressure_l2,pressure_spike,wall_seconds,compute_seconds,steps,closure_evaluations,energy_drift,md_atom_steps,md_atom_steps_avoided,");
    for &t in times {
        let _ = write!(csv, "{},", error_column(component, t));
    }
    if !times.is_empty() {
        csv.push_str("scored_points,");
    }
    csv.push_str("run_dir\n");
    for (k, r) in rows.iter().enumerate() {
        for v in &r.values {
            let _ = write!(csv, "{},", v.replace(',', ";"));
        }
        let s = &r.summary;
        let compute = s["time_breakdown_s"]["setup"].as_f64().unwrap_or(0.0) + s["time_breakdown_s"]["continuum"].as_f64().unwrap_or(0.0);
        let _ = write!(
            csv,
            "{},{},{},{},{},{},{compute:e},{},{},{},{:e},{:e},",
            field(s, &["method"]),
            field(s, &["status"]),
            field(s, &["errors", "pressure_l1"]),
            field(s, &["errors", "pressure_l2"]),
            field(s, &["errors", "pressure_spike"]),
            field(s, &["wall_seconds"]),
            field(s, &["steps"]),
            field(s, &["closure_evaluations"]),
            field(s, &["conservation", "energy_drift"]),
            s["md"]["atom_steps_done"].as_f64().unwrap_or(r.atom_steps),
            s["md"]["atom_steps_avoided"].as_f64().unwrap_or(0.0),
        );
        for k in 0..times.len() {
            match r.scores.get(k) {
                Some((e, _)) => {
                    let _ = write!(csv, "{e:e},");
                }
                None => csv.push(','),
            }
        }
        if !times.is_empty() {
            let _ = write!(csv, "{},", r.scores.first().map(|s| s.1.to_string()).unwrap_or_default());
        }
        let _ = writeln!(csv, "runs/{k:03}");
    }
    output::write_atomic(&out.join("report.csv"), csv.as_bytes())?;
    plot(rows, &out.join("report.png"), times, component)
}

/// Error against wall time on log-log axes, one series per method: pressure L1 over the jump,
/// or with a reference the eq. 7.12 error at the last reference time.
fn plot(rows: &[Row], path: &Path, times: &[f64], component: &str) -> Result<()> {
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for r in rows {
        let s = &r.summary;
        let e = if times.is_empty() { s["errors"]["pressure_l1"].as_f64() } else { r.scores.last().map(|s| s.0) };
        let (Some(t), Some(e)) = (s["wall_seconds"].as_f64(), e) else { continue };
        if s["status"] != "completed" || !(t > 0.0 && e > 0.0) {
            continue;
        }
        let method = field(s, &["method"]);
        match series.iter_mut().find(|(m, _)| *m == method) {
            Some((_, pts)) => pts.push((t, e)),
            None => series.push((method, vec![(t, e)])),
        }
    }
    for (_, pts) in &mut series {
        pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    }
    let refs: Vec<output::Series<'_>> = series.iter().map(|(m, p)| output::Series { label: m, points: p.clone(), line: true }).collect();
    match times.last() {
        Some(t) => {
            let sigma = format!("sigma_{}", component.trim_start_matches('s'));
            output::plot_loglog(
                path,
                &format!("{sigma} error against direct MD at {} ps", t * 1e12),
                "wall time (s)",
                &format!("eq. 7.12 error of {sigma}"),
                &refs,
            )
        }
        None => output::plot_loglog(path, "pressure error against wall time", "wall time (s)", "pressure L1 error / jump", &refs),
    }
}

/// Parses `--sweep` values and runs the report (for the CLI).
pub fn default_out(scene_path: &Path) -> PathBuf {
    let stem = scene_path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into());
    PathBuf::from("runs").join(format!("{stem}-report"))
}

/// Reads a report back (for tests and tools): the rows of `report.csv`.
pub fn read_csv(path: &Path) -> Result<Vec<Vec<String>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    Ok(text.lines().map(|l| l.split(',').map(str::to_string).collect()).collect())
}

/// A direct-MD reference (a scene's `[reference] solution = "direct-md"`, or `--reference`):
/// one stress component in slabs of the reference (unstrained) coordinate at a series of times,
/// as `md-worker direct --slab` writes it (`time_ps,slab_center_nm,sxx_gpa,...`, tension
/// positive).
///
/// This is the 1D form. The 2D form of eq. 7.12 (Eulerian x-y bins with atom counts, scored in
/// the current configuration over the bins holding most of a bulk bin's atoms) is not
/// implemented yet: it would add a frame type sampled at (x, y) and a mask, and feed the same
/// [`eq_7_12_sum`].
#[derive(Debug, Clone, PartialEq)]
pub struct DirectProfile {
    /// (time (s), slabs sorted by X: (X (m), stress (Pa))).
    pub frames: Vec<(f64, Vec<(f64, f64)>)>,
}

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
        let mut lines = text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty());
        let (_, header) = lines.next().ok_or_else(|| {
            anyhow::anyhow!("is empty; expected a header time_ps,slab_center_nm,sxx_gpa,... (`md-worker direct --slab` output)")
        })?;
        let cols: Vec<&str> = header.split(',').map(str::trim).collect();
        let col = |name: &str| {
            cols.iter().position(|c| *c == name).ok_or_else(|| {
                anyhow::anyhow!("line 1: no column `{name}` (found {}); expected `md-worker direct --slab` output", cols.join(","))
            })
        };
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
        Ok(DirectProfile { frames })
    }

    /// The slabs at time `t` (s), if the reference has that time.
    pub fn at(&self, t: f64) -> Option<&[(f64, f64)]> {
        self.frames
            .iter()
            .filter(|(ft, _)| (ft - t).abs() <= TIME_TOLERANCE_S)
            .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
            .map(|(_, r)| r.as_slice())
    }

    /// First and last time of the profile (s).
    pub fn time_range(&self) -> (f64, f64) {
        let t = self.frames.iter().map(|f| f.0);
        (t.clone().fold(f64::INFINITY, f64::min), t.fold(f64::NEG_INFINITY, f64::max))
    }

    /// The profile's times (ps), for messages.
    pub fn times_ps(&self) -> String {
        self.frames.iter().map(|(t, _)| format!("{}", (t * 1e15).round() / 1e3)).collect::<Vec<_>>().join(", ")
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

/// One eq. 7.12 score of a run: at `time` (s), from the snapshot nearest to it.
#[derive(Debug, Clone, PartialEq)]
pub struct Score {
    pub time: f64,
    pub snapshot_step: u64,
    pub snapshot_time: f64,
    pub error: f64,
    pub points: usize,
}

/// The eq. 7.12 error of `component` of the run in `run_dir` against `profile` at each of
/// `times` (s), each from the snapshot of `snapshots/index.csv` nearest to it (scored against
/// the profile's frame at the time asked for). The one implementation of the score: `mscale
/// run` calls it for a scene's `[reference] solution = "direct-md"`, `mscale report` reads it
/// back from the runs' summary.json.
pub fn score_run(profile: &DirectProfile, component: &str, times: &[f64], map: &ReferenceMap, run_dir: &Path) -> Result<Vec<Score>> {
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
        let points = read_x0_component(&path, component)?;
        let pts: Vec<(f64, f64)> = points.iter().map(|&(x0, s)| (map.x_ref(x0), s)).collect();
        let reference = profile.at(t).ok_or_else(|| {
            anyhow::anyhow!("the direct-MD reference has no frame at t = {} ps (it has {} ps)", t * 1e12, profile.times_ps())
        })?;
        let (error, n) = eq_7_12(reference, &pts, REFERENCE_WALL_M)
            .with_context(|| format!("eq. 7.12 of {component} of {} at t = {} ps", path.display(), t * 1e12))?;
        out.push(Score { time: t, snapshot_step: *step, snapshot_time: *ts, error, points: n });
    }
    Ok(out)
}

/// The summary.json `errors` of a run scored against a direct-MD reference: the eq. 7.12 error
/// per time (with the snapshot it came from), and a flat `<component>_error_<t>ps` per time
/// (the report's column names).
pub fn direct_md_errors_json(profile: &Path, component: &str, scores: &[Score]) -> Value {
    let mut m = serde_json::Map::new();
    m.insert("reference".into(), "direct-md".into());
    m.insert("profile".into(), profile.display().to_string().into());
    m.insert("component".into(), component.into());
    m.insert("measure".into(), "eq. 7.12: sqrt(sum (s_MD - s_MS)^2 / sum s_MD^2) over the material points in the reference coordinate, points within 1 nm of the bar's ends left out".into());
    m.insert(
        "times".into(),
        scores
            .iter()
            .map(|s| serde_json::json!({"time_ps": ps(s.time), "snapshot_step": s.snapshot_step, "snapshot_time_ps": ps(s.snapshot_time), "error": s.error, "points": s.points}))
            .collect::<Vec<_>>()
            .into(),
    );
    for s in scores {
        m.insert(error_column(component, s.time), s.error.into());
    }
    Value::Object(m)
}

/// A time (s) in ps, rounded to 1e-6 ps (the round-off of summed steps removed).
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
    format!("eq. 7.12 error of {component} against direct MD: {} ({} points)", parts.join(", "), scores.first().map_or(0, |s| s.points))
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
    bodies: Vec<(f64, f64, f64, f64)>,
}

impl ReferenceMap {
    pub fn of(scene: &scene::Scene) -> Result<ReferenceMap> {
        if scene.domain.dimension != 1 {
            anyhow::bail!("--reference scores sigma_xx along a 1D bar; scene `{}` has dimension {}", scene.name, scene.domain.dimension);
        }
        let mut b: Vec<(f64, f64, f64)> =
            scene.bodies.values().map(|b| (b.min[0], b.max[0], 1.0 + b.initial_strain.first().copied().unwrap_or(0.0))).collect();
        b.sort_by(|p, q| p.0.total_cmp(&q.0));
        let mut bodies = Vec::new();
        let mut prev: Option<(f64, f64)> = None; // (x0 max, X max) of the body before
        for (lo, hi, stretch) in b {
            let start = match prev {
                None => lo,
                Some((pmax, _)) if lo < pmax - 1e-9 * (hi - lo) => {
                    anyhow::bail!("bodies of scene `{}` overlap along x at {lo:e} m: cannot map them to one reference bar", scene.name)
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

/// `--reference FILE --reference-times T1,T2,...`: score every run's sigma_xx by eq. 7.12 at
/// these times (s).
#[derive(Debug, Clone)]
pub struct ReferenceSpec {
    pub path: PathBuf,
    pub profile: DirectProfile,
    /// (s).
    pub times: Vec<f64>,
    /// The same times as given (ps).
    pub times_ps: Vec<f64>,
}

impl ReferenceSpec {
    /// Reads the reference and checks that it has every requested time.
    pub fn load(path: &Path, times_ps: &[f64]) -> Result<ReferenceSpec> {
        if times_ps.is_empty() {
            anyhow::bail!("--reference needs --reference-times T1,T2,... (ps)");
        }
        let profile = DirectProfile::read(path)?;
        let mut times = Vec::new();
        for &t in times_ps {
            if !(t.is_finite() && t > 0.0) {
                anyhow::bail!("--reference-times: {t} ps is not a positive time");
            }
            if profile.at(t * 1e-12).is_none() {
                anyhow::bail!(
                    "--reference-times: the direct-MD reference {} has no rows at t = {t} ps (it has {} ps)",
                    path.display(),
                    profile.times_ps()
                );
            }
            times.push(t * 1e-12);
        }
        Ok(ReferenceSpec { path: path.to_path_buf(), profile, times, times_ps: times_ps.to_vec() })
    }

    /// Snapshot count that puts a snapshot at every reference time: every = gcd of their step
    /// numbers and the run's step count. Refuses times that are not whole steps or lie after
    /// the end.
    pub fn snapshots(&self, loaded: &scene::LoadedScene) -> Result<usize> {
        let mut every = loaded.steps;
        for &t in &self.times {
            let n = (t / loaded.dt).round();
            if (n * loaded.dt - t).abs() > 1e-6 * loaded.dt {
                anyhow::bail!(
                    "--reference-times: {} ps is not a whole number of continuum steps of {} ps in scene `{}`; choose scheme.timestep dividing it",
                    t * 1e12,
                    loaded.dt * 1e12,
                    loaded.scene.name
                );
            }
            if n as u64 > loaded.steps {
                anyhow::bail!(
                    "--reference-times: {} ps lies after the end time {} ps of scene `{}`",
                    t * 1e12,
                    loaded.steps as f64 * loaded.dt * 1e12,
                    loaded.scene.name
                );
            }
            every = gcd(every, n as u64);
        }
        Ok((loaded.steps / every.max(1)) as usize)
    }

    /// eq. 7.12 error of sigma_xx of the run in `run_dir` at each reference time:
    /// (error, points scored) per time ([`score_run`]).
    pub fn score(&self, map: &ReferenceMap, run_dir: &Path) -> Result<Vec<(f64, usize)>> {
        Ok(score_run(&self.profile, "sxx", &self.times, map, run_dir)?.into_iter().map(|s| (s.error, s.points)).collect())
    }

    /// The `--set` overrides that make a scene's runs score themselves against this reference.
    pub fn overrides(&self) -> Vec<String> {
        let path = self.path.canonicalize().unwrap_or_else(|_| self.path.clone());
        let times: Vec<String> = self.times_ps.iter().map(|t| format!("{t:?}")).collect();
        vec![
            "reference.solution=\"direct-md\"".to_string(),
            format!("reference.profile={}", serde_json::Value::from(path.display().to_string())),
            format!("reference.times_ps=[{}]", times.join(", ")),
            "reference.component=\"sxx\"".to_string(),
        ]
    }
}

fn gcd(a: u64, b: u64) -> u64 {
    if b == 0 { a } else { gcd(b, a % b) }
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

/// MD atom-steps of a scene: per md body, points x atoms per box x MD steps per box.
pub fn md_atom_steps(loaded: &scene::LoadedScene) -> Result<f64> {
    let (per_body, _) = crate::setup::work_size(&loaded.scene);
    let mut total = 0.0;
    for (name, n) in per_body {
        let Some(scene::Material::Md(m)) = loaded.scene.bodies.get(&name).map(|b| &b.material) else { continue };
        let steps = loaded.steps as f64 * (loaded.dt / (m.timestep_fs * 1e-15)).round() + m.relax_steps as f64;
        total += n as f64 * crate::md::atoms_per_box(m)? as f64 * steps;
    }
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_joined_key_sets_every_key_to_the_value() {
        let sweeps: Vec<Sweep> = ["a+b=1,2", "c=x"].iter().map(|s| s.parse().expect("sweep")).collect();
        assert_eq!(combinations(&sweeps), [vec!["a=1", "b=1", "c=x"], vec!["a=2", "b=2", "c=x"]]);
        assert_eq!(value_combinations(&sweeps), [vec!["1", "x"], vec!["2", "x"]]);
        assert!("a+=1".parse::<Sweep>().is_err());
    }

    #[test]
    fn replicas_are_averaged_per_setting() {
        let sweeps: Vec<Sweep> = ["cells=60,120", "seed=1,2"].iter().map(|s| s.parse().expect("sweep")).collect();
        let row = |cells: &str, seed: &str, wall: f64, e: f64| Row {
            values: vec![cells.into(), seed.into()],
            summary: serde_json::json!({"status": "completed", "wall_seconds": wall}),
            atom_steps: 0.0,
            scores: vec![(e, 10)],
        };
        let rows = [row("60", "1", 1.0, 0.1), row("60", "2", 3.0, 0.3), row("120", "1", 5.0, 0.2)];
        let text = replica_summary(&sweeps, 1, &rows, &[5e-12]);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "cells,replicas,wall_seconds_mean,wall_seconds_std,sxx_error_5ps_mean,sxx_error_5ps_std");
        let f: Vec<f64> = lines[1].split(',').map(|v| v.parse().expect("number")).collect();
        assert_eq!(f[..4], [60.0, 2.0, 2.0, 2f64.sqrt()]);
        assert!((f[4] - 0.2).abs() < 1e-15 && (f[5] - 0.02f64.sqrt()).abs() < 1e-15, "{f:?}");
        assert_eq!(lines[2], "120,1,5e0,,2e-1,");
    }

    /// Ten 1 m slabs, -10 left of X = 5, 0 right of it.
    fn step_profile() -> Vec<(f64, f64)> {
        (0..10).map(|i| (i as f64 + 0.5, if i < 5 { -10.0 } else { 0.0 })).collect()
    }

    #[test]
    fn eq_7_12_is_zero_for_the_reference_itself() {
        let r = step_profile();
        let (e, n) = eq_7_12(&r, &r, 0.0).expect("score");
        assert_eq!((e, n), (0.0, 10));
        // Points between slab centres see the linear interpolation.
        let mid: Vec<(f64, f64)> = (0..9).map(|i| (i as f64 + 1.0, interpolate(&r, i as f64 + 1.0))).collect();
        assert_eq!(eq_7_12(&r, &mid, 0.0).expect("score").0, 0.0);
        assert_eq!(interpolate(&r, 5.0), -5.0);
        assert_eq!(interpolate(&r, -3.0), -10.0);
        assert_eq!(interpolate(&r, 30.0), 0.0);
    }

    #[test]
    fn eq_7_12_of_a_front_shifted_by_one_slab() {
        // The run's front lags one slab: the point at X = 5.5 still reads -10 where the
        // reference reads 0. sum diff^2 = 100, sum ref^2 = 5 x 100: eps = sqrt(1/5).
        let r = step_profile();
        let run: Vec<(f64, f64)> = (0..10).map(|i| (i as f64 + 0.5, if i < 6 { -10.0 } else { 0.0 })).collect();
        let (e, n) = eq_7_12(&r, &run, 0.0).expect("score");
        assert_eq!(n, 10);
        assert!((e - 0.2f64.sqrt()).abs() < 1e-15, "{e}");
        // A wall of 1 m leaves out the points at 0.5 and 9.5 (within 1 m of 0 and 10): the
        // reference sum loses one -10 point.
        let (e, n) = eq_7_12(&r, &run, 1.0).expect("score");
        assert_eq!(n, 8);
        assert!((e - 0.25f64.sqrt()).abs() < 1e-15, "{e}");
        // Nothing scored, or a zero reference, is an error rather than a number.
        assert!(eq_7_12(&r, &[(20.0, 1.0)], 0.0).unwrap_err().to_string().contains("no material point"));
        let zero: Vec<(f64, f64)> = r.iter().map(|p| (p.0, 0.0)).collect();
        assert!(eq_7_12(&zero, &run, 0.0).unwrap_err().to_string().contains("undefined"));
    }

    #[test]
    fn direct_profile_groups_times_and_refuses_bad_files() {
        let text = "time_ps,slab_center_nm,sxx_gpa,syy_gpa\n0,2,-1,0\n0,1,-2,0\n4.9999999999996705,1,3,0\n5.000000000000004,2,4,0\n";
        let p = DirectProfile::parse(text).expect("parse");
        assert_eq!(p.frames.len(), 2);
        assert_eq!(p.at(0.0).expect("t=0"), &[(1e-9, -2e9), (2e-9, -1e9)]);
        let at5 = p.at(5e-12).expect("t=5");
        assert_eq!(at5.len(), 2);
        assert!((at5[1].1 - 4e9).abs() < 1e-3);
        assert!(p.at(1e-12).is_none());
        let e = DirectProfile::parse("time_ps,x,sxx_gpa\n0,1,2\n").unwrap_err().to_string();
        assert!(e.contains("no column `slab_center_nm`"), "{e}");
        let e = DirectProfile::parse("time_ps,slab_center_nm,sxx_gpa\n0,1,2\n0,2,oops\n").unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("sxx_gpa"), "{e}");
        let e = DirectProfile::parse("time_ps,slab_center_nm,sxx_gpa\n0,1,2\n").unwrap_err().to_string();
        assert!(e.contains("at least two slabs"), "{e}");
    }

    /// The elastic twin as these tests were written for (60 cells, 0.25 ps, the interface at
    /// 51.11 nm), then `sets`.
    fn elastic_bar(sets: &[&str]) -> scene::LoadedScene {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cu-shock-1d-elastic.toml");
        let pinned = [
            "domain.cells=[60]",
            "scheme.timestep=0.25e-12",
            "scheme.integrator=dhakal",
            "bodies.compressed.max=[51.11e-9]",
            "bodies.relaxed.min=[51.11e-9]",
        ];
        scene::load(&path, &pinned.iter().chain(sets).map(|s| s.to_string()).collect::<Vec<_>>()).expect("scene")
    }

    #[test]
    fn reference_map_unstrains_the_compressed_body() {
        let l = elastic_bar(&[]);
        let m = ReferenceMap::of(&l.scene).expect("map");
        let (a, b) = (51.11e-9, 105.73875e-9);
        assert_eq!(m.x_ref(0.0), 0.0);
        assert!((m.x_ref(0.95 * 10e-9) - 10e-9).abs() < 1e-20);
        // The interface moves to 51.11 / 0.95 nm; the relaxed body keeps its length.
        assert!((m.x_ref(a) - a / 0.95).abs() < 1e-20);
        assert!((m.x_ref(b) - (a / 0.95 + (b - a))).abs() < 1e-20);
    }

    #[test]
    fn snapshots_land_on_the_reference_times() {
        let dir = tempfile::tempdir().expect("tempdir");
        let csv = dir.path().join("ref.csv");
        let mut text = String::from("time_ps,slab_center_nm,sxx_gpa\n");
        for t in [0.0, 5.0, 10.0] {
            for k in 0..60 {
                text.push_str(&format!("{t},{},{}\n", 0.90375 + 1.8075 * k as f64, if k < 30 { -9.0 } else { 0.0 }));
            }
        }
        std::fs::write(&csv, text).expect("write");
        let spec = ReferenceSpec::load(&csv, &[5.0, 10.0]).expect("spec");
        // dt 0.25 ps, 40 steps: steps 20 and 40, a snapshot every 20 steps.
        assert_eq!(spec.snapshots(&elastic_bar(&[])).expect("snapshots"), 2);
        assert_eq!(spec.snapshots(&elastic_bar(&["scheme.timestep=0.05e-12"])).expect("snapshots"), 2);
        let e = spec.snapshots(&elastic_bar(&["scheme.timestep=0.3e-12"])).unwrap_err().to_string();
        assert!(e.contains("not a whole number of continuum steps"), "{e}");
        // (The scene's own reference scores at 5 ps only here, so the scene is valid.)
        let e = spec.snapshots(&elastic_bar(&["scheme.end_time=8e-12", "reference.times_ps=[5.0]"])).unwrap_err().to_string();
        assert!(e.contains("after the end time"), "{e}");
        let e = ReferenceSpec::load(&csv, &[7.0]).unwrap_err().to_string();
        assert!(e.contains("no rows at t = 7 ps") && e.contains("0, 5, 10"), "{e}");
        assert!(ReferenceSpec::load(&csv, &[]).is_err());
    }

    #[test]
    fn a_run_directory_is_scored_at_each_time() {
        let dir = tempfile::tempdir().expect("tempdir");
        let csv = dir.path().join("ref.csv");
        // Reference X: 0..100 nm in 10 nm slabs, -2 GPa left of 50 nm, -1 GPa right of it.
        let mut text = String::from("time_ps,slab_center_nm,sxx_gpa\n");
        for t in [5.0, 10.0] {
            for k in 0..10 {
                text.push_str(&format!("{t},{},{}\n", 10.0 * k as f64 + 5.0, if k < 5 { -2.0 } else { -1.0 }));
            }
        }
        std::fs::write(&csv, text).expect("write");
        let spec = ReferenceSpec::load(&csv, &[5.0, 10.0]).expect("spec");
        let run = dir.path().join("run");
        std::fs::create_dir_all(run.join("snapshots")).expect("mkdir");
        std::fs::write(run.join("snapshots/index.csv"), "step,time,file\n0,0e0,a.csv\n20,5e-12,b.csv\n40,1e-11,c.csv\n").expect("index");
        // Points at the slab centres in the reference coordinate; the map is the identity.
        let map = ReferenceMap { bodies: vec![(0.0, 100e-9, 0.0, 1.0)] };
        let table = |f: &dyn Fn(usize) -> f64| {
            let mut s = String::from("id,x0,x,vx,mass,volume,density,pressure,sxx,syy,szz,sxy,sxz,syz\n");
            for k in 0..10 {
                let x = (10.0 * k as f64 + 5.0) * 1e-9;
                s.push_str(&format!("{k},{x:e},{x:e},0,1,1,1,0,{:e},0,0,0,0,0\n", f(k)));
            }
            s
        };
        std::fs::write(run.join("snapshots/b.csv"), table(&|k| if k < 5 { -2e9 } else { -1e9 })).expect("b");
        // At 10 ps one point right of the jump reads -2 GPa: sqrt(1 / (5 x 4 + 5 x 1)) = 0.2.
        std::fs::write(run.join("snapshots/c.csv"), table(&|k| if k < 6 { -2e9 } else { -1e9 })).expect("c");
        let s = spec.score(&map, &run).expect("score");
        assert_eq!(s[0], (0.0, 10));
        assert!((s[1].0 - 0.2).abs() < 1e-12 && s[1].1 == 10, "{s:?}");
        std::fs::remove_file(run.join("snapshots/c.csv")).expect("rm");
        assert!(spec.score(&map, &run).unwrap_err().to_string().contains("c.csv"));
    }
}
