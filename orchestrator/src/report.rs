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
//! reads it from there. A 2D scene with a 2D profile (`md-worker direct --dimension 2`: Eulerian
//! x-y bins) is scored by the same code over the particles in the bulk-like bins
//! ([`eq_7_12_2d`]); `--reference` gives 1D bars only.

use crate::output;
use crate::reference::error_column;
pub use crate::reference::*;
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
        // Commas inside brackets belong to one value: `domain.cells=[8,8],[16,16]` is two values.
        let mut parts = Vec::new();
        let (mut depth, mut start) = (0i32, 0);
        for (i, ch) in values.char_indices() {
            match ch {
                '[' | '{' => depth += 1,
                ']' | '}' => depth -= 1,
                ',' if depth == 0 => {
                    parts.push(&values[start..i]);
                    start = i + 1;
                }
                _ => {}
            }
        }
        parts.push(&values[start..]);
        let values: Vec<String> = parts.into_iter().map(|v| v.trim().to_string()).filter(|v| !v.is_empty()).collect();
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
        let atom_steps = md_atom_steps(&l);
        loaded.push((l, atom_steps));
    }
    // The times and component scored (the columns): those of the reference every run has.
    let (times, component) = match loaded.first().and_then(|(l, _)| l.scene.reference.as_ref()) {
        Some(scene::Reference::DirectMd(r)) => {
            (r.times_ps.iter().map(|t| t * 1e-12).collect::<Vec<f64>>(), r.component.as_str().to_string())
        }
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
    // Runs against a manufactured solution add its three L2 errors.
    let manufactured = scored_against(rows, "manufactured");
    if manufactured {
        csv.push_str("displacement_l2,velocity_l2,stress_l2,");
    }
    // Runs against a heat series add its RMS errors at the end (points, nodes, nodes off the
    // Dirichlet faces) and the FLIP fraction beta that the thesis's tables compare.
    let heat = scored_against(rows, "heat-series");
    if heat {
        csv.push_str("flip_fraction,dirichlet,end_time,rms_points,rms_nodes,rms_interior_nodes,");
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
        if manufactured {
            for q in ["displacement_l2", "velocity_l2", "stress_l2"] {
                let _ = write!(csv, "{},", field(s, &["errors", q]));
            }
        }
        if heat {
            for q in ["flip_fraction", "dirichlet", "time_s", "rms_points", "rms_nodes", "rms_interior_nodes"] {
                let _ = write!(csv, "{},", field(s, &["errors", q]));
            }
        }
        let _ = writeln!(csv, "runs/{k:03}");
    }
    output::write_atomic(&out.join("report.csv"), csv.as_bytes())?;
    plot(rows, &out.join("report.png"), times, component)
}

/// Whether the rows were scored against the reference `solution` (summary.json `errors.reference`).
fn scored_against(rows: &[Row], solution: &str) -> bool {
    rows.iter().any(|r| r.summary["errors"]["reference"] == solution)
}

/// Error against wall time on log-log axes, one series per method: pressure L1 over the jump,
/// the displacement L2 against a manufactured solution, the points' RMS against a heat series
/// (one series per method and FLIP fraction), or with a direct-MD reference the eq. 7.12 error
/// at the last reference time.
fn plot(rows: &[Row], path: &Path, times: &[f64], component: &str) -> Result<()> {
    let manufactured = scored_against(rows, "manufactured");
    let heat = scored_against(rows, "heat-series");
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for r in rows {
        let s = &r.summary;
        let e = if manufactured {
            s["errors"]["displacement_l2"].as_f64()
        } else if heat {
            s["errors"]["rms_points"].as_f64()
        } else if times.is_empty() {
            s["errors"]["pressure_l1"].as_f64()
        } else {
            r.scores.last().map(|s| s.0)
        };
        let (Some(t), Some(e)) = (s["wall_seconds"].as_f64(), e) else { continue };
        if s["status"] != "completed" || !(t > 0.0 && e > 0.0) {
            continue;
        }
        // A heat series: one line per scheme and FLIP fraction (the tables' beta columns).
        let method =
            if heat { format!("{} beta {}", field(s, &["method"]), field(s, &["errors", "flip_fraction"])) } else { field(s, &["method"]) };
        match series.iter_mut().find(|(m, _)| *m == method) {
            Some((_, pts)) => pts.push((t, e)),
            None => series.push((method, vec![(t, e)])),
        }
    }
    // Each line in order of cost; a heat series' runs (fractions of a second, all schemes the
    // same work at rest) in sweep order instead, so that timing noise does not zigzag the lines.
    if !heat {
        for (_, pts) in &mut series {
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
    }
    let refs: Vec<output::Series<'_>> = series.iter().map(|(m, p)| output::Series { label: m, points: p.clone(), line: true }).collect();
    if manufactured {
        return output::plot_loglog(
            path,
            "displacement error against wall time (manufactured solution)",
            "wall time (s)",
            "displacement L2 error",
            &refs,
        );
    }
    if heat {
        return output::plot_loglog(
            path,
            "points' RMS error against the heat series at the end, against wall time",
            "wall time (s)",
            "RMS error of the points' values",
            &refs,
        );
    }
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
        Ok(score_run(&self.profile, "sxx", &self.times, Some(map), run_dir)?.into_iter().map(|s| (s.error, s.points)).collect())
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

/// MD atom-steps of a scene: per md body, points x atoms per box x MD steps per box.
pub fn md_atom_steps(loaded: &scene::LoadedScene) -> f64 {
    let mut total = 0.0;
    for (body, m) in loaded.resolved.md_bodies() {
        let steps = loaded.steps as f64 * (loaded.dt / (m.timestep_fs * 1e-15)).round() + m.relax_steps as f64;
        total += body.points as f64 * m.atoms_per_box as f64 * steps;
    }
    total
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
        let cells: Sweep = "domain.cells=[8,8], [16,16],[32,32]".parse().expect("sweep");
        assert_eq!(cells.values, ["[8,8]", "[16,16]", "[32,32]"]);
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

    /// The 2D profile of `md-worker direct --dimension 2`: two frames of 2 x 2 bins of 2 nm
    /// (a comment line first), the bulk bin's atoms from the first frame, the mask and the
    /// periodic x of eq. 7.12 in 2D, and the files it refuses.
    #[test]
    fn direct_profile_2d_scores_the_particles_in_bulk_bins() {
        let head =
            "# md-worker direct --dimension 2 ...\ntime_ps,bin_x_nm,bin_y_nm,atoms,vx_km_s,vy_km_s,sxx_gpa,syy_gpa,szz_gpa,sxy_gpa\n";
        let rows = "0,1,1,500,0,-2.5,0,-1,0,0\n0,3,1,500,0,-2.5,0,-1,0,0\n0,1,3,500,0,-2.5,0,-1,0,0\n0,3,3,20,0,-2.5,0,-1,0,0\n\
                    5.000000000000004,1,1,750,0,0,0,-100,0,0\n5.000000000000004,3,1,700,0,0,0,-200,0,0\n5.000000000000004,1,3,399,0,0,0,-50,0,0\n5.000000000000004,3,3,0,0,0,0,0,0,0\n";
        let p = DirectProfile::parse_component(&format!("{head}{rows}"), "syy").expect("parse");
        assert!(p.is_2d() && p.frames.is_empty());
        assert_eq!(p.bulk_atoms(), 500);
        assert!(p.has_frame(5e-12) && !p.has_frame(1e-12));
        let (t0, t1) = p.time_range();
        assert!(t0 == 0.0 && (t1 - 5e-12).abs() < 1e-15, "{t0} {t1}");
        let f = p.bins_at(5e-12).expect("t=5");
        assert_eq!((f.nx, f.ny), (2, 2));
        assert!((f.bin - 2e-9).abs() < 1e-24);
        assert_eq!(f.atoms, vec![750, 700, 399, 0]);
        // Bin (0,0) -100, (1,0) -200 (one particle given by a periodic image of x), bin (0,1)
        // holds 399 < 400 atoms and bin (1,1) none: left out, as is a particle above the bins.
        let pts = [
            (0.5e-9, 0.5e-9, -90e9),
            (4.0e-9 + 3.5e-9, 1.5e-9, -180e9),
            (3.0e-9, 0.2e-9, -200e9),
            (1e-9, 3e-9, -50e9),
            (3e-9, 3e-9, 0.0),
            (1e-9, 5e-9, 0.0),
        ];
        let (e, n, out) = eq_7_12_2d(f, &pts, 0.8 * 500.0).expect("score");
        assert_eq!((n, out), (3, 3));
        let want = ((10e9f64.powi(2) + 20e9f64.powi(2)) / (100e9f64.powi(2) + 2.0 * 200e9f64.powi(2))).sqrt();
        assert!((e - want).abs() < 1e-14, "{e} vs {want}");
        assert!(eq_7_12_2d(f, &pts[3..], 400.0).unwrap_err().to_string().contains("no particle"));
        // Bins not from the origin, or rows that are not whole rows of x.
        let e = DirectProfile::parse(&format!("{head}0,2,1,500,0,0,0,-1,0,0\n0,4,1,500,0,0,0,-1,0,0\n")).unwrap_err().to_string();
        assert!(e.contains("not (b/2, b/2)"), "{e}");
        let e = DirectProfile::parse(&format!("{head}0,1,1,500,0,0,0,-1,0,0\n0,3,1,500,0,0,0,-1,0,0\n0,1,3,5,0,0,0,-1,0,0\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("whole number of rows"), "{e}");
        let e = DirectProfile::parse(&format!("{head}0,1,1,1.5,0,0,0,-1,0,0\n")).unwrap_err().to_string();
        assert!(e.contains("not a count"), "{e}");
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
