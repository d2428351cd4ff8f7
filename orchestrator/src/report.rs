//! `mscale report error-vs-time`: run every combination of parameter sweeps of one scene and
//! tabulate error against cost, the question users ask before trusting a setting.

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
        if key.trim().is_empty() || values.is_empty() {
            return Err(format!("expected --sweep key=v1,v2,..., got `{s}`"));
        }
        Ok(Sweep { key: key.trim().to_string(), values })
    }
}

/// Every combination of the sweeps, as lists of `key=value` overrides (first sweep slowest).
pub fn combinations(sweeps: &[Sweep]) -> Vec<Vec<String>> {
    let mut out = vec![Vec::new()];
    for s in sweeps {
        out = out
            .into_iter()
            .flat_map(|prefix| {
                s.values.iter().map(move |v| {
                    let mut c = prefix.clone();
                    c.push(format!("{}={v}", s.key));
                    c
                })
            })
            .collect();
    }
    out
}

/// Overrides applied to every run of a report: only the final state is written, so the time
/// measured is the solver's, not the output's.
const REPORT_OUTPUT: [&str; 4] = ["output.snapshots=1", "output.vtk=false", "output.plots=false", "output.particles=true"];

/// One finished run of a report.
pub struct Row {
    pub values: Vec<String>,
    pub summary: Value,
}

/// Validates every combination first (a bad value is refused before anything runs), then runs
/// them one after another and writes `report.csv` and `report.png` in `out`.
pub fn error_vs_time(scene_path: &Path, sets: &[String], sweeps: &[Sweep], out: &Path, workers: &[String]) -> Result<Vec<Row>, ReportError> {
    let combos = combinations(sweeps);
    let mut loaded = Vec::new();
    for combo in &combos {
        let all: Vec<String> = sets.iter().cloned().chain(REPORT_OUTPUT.iter().map(|s| s.to_string())).chain(combo.iter().cloned()).collect();
        loaded.push(scene::load(scene_path, &all).map_err(ReportError::Scene)?);
    }
    let mut rows = Vec::new();
    for (k, (combo, l)) in combos.iter().zip(&loaded).enumerate() {
        tracing::info!("report run {}/{}: {}", k + 1, combos.len(), combo.join(" "));
        let mut opts = RunOptions::new(out.join("runs").join(format!("{k:03}")), std::env::args().collect());
        opts.progress_bar = false;
        opts.workers = workers.to_vec();
        let summary = match run::run(l, &opts).map_err(ReportError::Io)? {
            Outcome::Completed(s) | Outcome::Failed(s, _) => s,
            Outcome::Cancelled { step, .. } => return Err(ReportError::Io(anyhow::anyhow!("report run {k} was cancelled at step {step}"))),
        };
        let values = combo.iter().map(|c| c.split_once('=').map(|(_, v)| v.to_string()).unwrap_or_default()).collect();
        rows.push(Row { values, summary });
        write_outputs(sweeps, &rows, out).map_err(ReportError::Io)?;
    }
    Ok(rows)
}

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{0}")]
    Scene(SceneError),
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

fn write_outputs(sweeps: &[Sweep], rows: &[Row], out: &Path) -> Result<()> {
    let mut csv = String::new();
    for s in sweeps {
        let _ = write!(csv, "{},", s.key);
    }
    csv.push_str("method,status,pressure_l1,pressure_l2,pressure_spike,wall_seconds,compute_seconds,steps,closure_evaluations,energy_drift,run_dir\n");
    for (k, r) in rows.iter().enumerate() {
        for v in &r.values {
            let _ = write!(csv, "{},", v.replace(',', ";"));
        }
        let s = &r.summary;
        let compute = s["time_breakdown_s"]["setup"].as_f64().unwrap_or(0.0) + s["time_breakdown_s"]["continuum"].as_f64().unwrap_or(0.0);
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{compute:e},{},{},{},runs/{k:03}",
            field(s, &["method"]),
            field(s, &["status"]),
            field(s, &["errors", "pressure_l1"]),
            field(s, &["errors", "pressure_l2"]),
            field(s, &["errors", "pressure_spike"]),
            field(s, &["wall_seconds"]),
            field(s, &["steps"]),
            field(s, &["closure_evaluations"]),
            field(s, &["conservation", "energy_drift"]),
        );
    }
    output::write_atomic(&out.join("report.csv"), csv.as_bytes())?;
    plot(rows, &out.join("report.png"))
}

/// Error (pressure L1 over the jump) against wall time on log-log axes, one series per method.
fn plot(rows: &[Row], path: &Path) -> Result<()> {
    let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
    for r in rows {
        let s = &r.summary;
        let (Some(t), Some(e)) = (s["wall_seconds"].as_f64(), s["errors"]["pressure_l1"].as_f64()) else { continue };
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
    output::plot_loglog(path, "pressure error against wall time", "wall time (s)", "pressure L1 error / jump", &refs)
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
