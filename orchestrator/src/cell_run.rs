//! `mscale run` / `mscale check` / `mscale report error-vs-time` of a cell scene
//! (`kind = "cell"`): the 1D Poisson-Nernst-Planck full cell of the `mscale-cell` crate.
//!
//! The scene file goes through the same `--set` overrides as every scene
//! ([`scene::apply_overrides`]) and is then handed to the cell crate's own typed scene; its
//! errors become [`SceneError`]s (exit code 2). A run writes, like an MPM run, its directory with
//! `scene.resolved.toml`, `summary.json` (status, wall_seconds, steps, state_digest, totals,
//! step statistics, time breakdown, provenance), `log.txt`-free progress on stderr (a bar on a
//! terminal), and `profiles/profile_<step>.csv` (+ PNG) at the scene's output times and
//! `profiles/profile_final.csv`.
//!
//! Checkpoints: the integrator restarts at every output time and every switch
//! ([`solver::Restart`]), so a checkpoint is the newest restart point (state, switch states,
//! first step, statistics) with the profile index written so far, in the checkpoint file format
//! of [`crate::checkpoint`]. `--checkpoint-every N` writes one at the first restart point after
//! each N accepted steps; a stop on request (SIGINT/SIGTERM, the job service) writes the newest
//! restart point and returns [`Outcome::Cancelled`]; `--resume` continues from the newest good
//! checkpoint to the state of the run that never stopped, bit for bit (the work since the
//! restart point is done again).

use crate::checkpoint;
use crate::output::{self, Series};
use crate::report::{self, Sweep};
use crate::run::{Outcome, Progress, RunOptions};
use crate::scene::{self, SceneError};
use anyhow::{Context, Result};
use mscale_cell::solver::{self, Control, Restart, Settings, Snapshot, Stats};
use mscale_cell::{CellScene, Model};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::time::Instant;

/// A cell scene read from a file.
#[derive(Debug, Clone)]
pub struct LoadedCell {
    pub scene: CellScene,
    pub path: PathBuf,
    pub text: String,
}

/// A cell run's checkpoint: a restart point of the integrator and what the run driver has
/// written up to it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CellCheckpoint {
    /// Always "cell" (an MPM checkpoint does not decode as this).
    pub kind: String,
    /// SHA-256 of the resolved scene the run was started with.
    pub scene_sha256: String,
    pub restart: Restart,
    /// Lines of profiles/index.csv written up to the restart point.
    pub profile_index: Vec<String>,
}

impl checkpoint::Saved for CellCheckpoint {
    fn step(&self) -> u64 {
        self.restart.stats.steps
    }
}

/// Whether the file is a cell scene (`kind = "cell"`); false when it cannot be read or parsed
/// (the MPM loader then reports the problem).
pub fn is_cell_scene(path: &Path) -> bool {
    std::fs::read_to_string(path).is_ok_and(|t| mscale_cell::scene::is_cell_text(&t))
}

/// Reads, overrides, parses and validates a cell scene.
pub fn load(path: &Path, sets: &[String]) -> Result<LoadedCell, SceneError> {
    let file = path.display().to_string();
    let bad =
        |problem: String| SceneError { file: file.clone(), location: String::new(), key: String::new(), value: String::new(), problem };
    let text = std::fs::read_to_string(path).map_err(|e| bad(format!("cannot read the scene file: {e}")))?;
    let (text, overrides): (String, BTreeMap<String, String>) = scene::apply_overrides(&file, &text, sets)?;
    let default_name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "cell".into());
    let scene = mscale_cell::scene::parse(&text, &overrides, &default_name).map_err(|e| SceneError {
        file: file.clone(),
        location: e.location,
        key: e.key,
        value: e.value,
        problem: e.problem,
    })?;
    Ok(LoadedCell { scene, path: path.to_path_buf(), text })
}

/// `mscale check`: the resolved scene and the size of the work.
pub fn check_text(loaded: &LoadedCell) -> String {
    let s = &loaded.scene;
    let model = Model::new(s);
    format!(
        "{}\n# work\n# cells = {}\n# unknowns = {}\n# dx_nm = {:e}\n# interfaces = {}\n# explicit_euler_bound_s = {:.3e}\n",
        s.to_toml(),
        model.n,
        model.len(),
        model.dx,
        model.interfaces.len(),
        s.explicit_bound()
    )
}

/// Refuses a restart point that does not belong to this model and run: a time outside
/// [0, end time] (a time of -9e18 s made the integrator run for ever), a state of another
/// length or with a non-finite value, an unusable first step, more outputs done than exist.
fn check_restart(r: &Restart, model: &Model, settings: &Settings, y_init: &[f64]) -> Result<()> {
    let end = settings.end_time;
    anyhow::ensure!(r.t.is_finite() && r.t >= 0.0 && r.t <= end, "its time {:e} s lies outside the run's [0, {end:e}] s", r.t);
    anyhow::ensure!(r.y.len() == y_init.len(), "its state has {} values, the scene's model {}", r.y.len(), y_init.len());
    if let Some(k) = r.y.iter().position(|v| !v.is_finite()) {
        anyhow::bail!("its state holds the non-finite value {} at index {k}", r.y[k]);
    }
    let open = model.initial_open(y_init).len();
    anyhow::ensure!(r.open.len() == open, "it has {} interface states, the scene's model {open}", r.open.len());
    anyhow::ensure!(r.h0.is_finite() && r.h0 > 0.0, "its first step {:e} is not a positive number", r.h0);
    anyhow::ensure!(
        r.outputs_done <= settings.output_times.len(),
        "it has {} outputs done of the scene's {}",
        r.outputs_done,
        settings.output_times.len()
    );
    Ok(())
}

fn finite_or_null(v: f64) -> Value {
    if v.is_finite() { json!(v) } else { Value::Null }
}

/// The profile CSV of a state: x_nm,p_per_nm3,n_per_nm3,phi_v,charge_e_per_nm3.
pub fn profile_csv(model: &Model, y: &[f64]) -> String {
    let mut out = String::from("x_nm,p_per_nm3,n_per_nm3,phi_v,charge_e_per_nm3\n");
    for i in 0..model.n {
        let (p, n, phi) = (y[3 * i], y[3 * i + 1], y[3 * i + 2]);
        out.push_str(&format!("{:e},{:e},{:e},{:e},{:e}\n", model.x[i], p, n, phi, p - n));
    }
    out
}

fn write_profile(model: &Model, y: &[f64], t: f64, dir: &Path, stem: &str, plots: bool) -> Result<()> {
    output::write_atomic(&dir.join(format!("{stem}.csv")), profile_csv(model, y).as_bytes())?;
    if plots {
        let pts = |k: usize| -> Vec<(f64, f64)> { (0..model.n).map(|i| (model.x[i], y[3 * i + k])).collect() };
        let charge: Vec<(f64, f64)> = (0..model.n).map(|i| (model.x[i], y[3 * i] - y[3 * i + 1])).collect();
        output::plot_profile(
            &dir.join(format!("{stem}.png")),
            &format!("concentrations at t = {t:.4e} s"),
            "x (nm)",
            "1/nm^3",
            &[
                Series { label: "p (cations)", points: pts(0), line: true },
                Series { label: "n (electrons | anions)", points: pts(1), line: true },
                Series { label: "p - n (e/nm^3)", points: charge, line: true },
            ],
        )?;
        output::plot_profile(
            &dir.join(format!("{stem}_phi.png")),
            &format!("potential at t = {t:.4e} s"),
            "x (nm)",
            "phi (V)",
            &[Series { label: "phi", points: pts(2), line: true }],
        )?;
    }
    Ok(())
}

fn totals_json(model: &Model, y: &[f64]) -> Value {
    let t = model.totals(y);
    json!({
        "cations_per_nm2": t.cations,
        "electrons_per_nm2": t.electrons,
        "anions_per_nm2": t.anions,
        "cathode_electrons_per_nm2": t.cathode_electrons,
        "net_charge_e_per_nm2": t.charge,
        "min_p_per_nm3": t.min_p,
    })
}

/// Default run directory: `runs/<scene>-<UTC timestamp>` (as for MPM scenes).
pub fn default_out_dir(scene: &CellScene) -> PathBuf {
    crate::run::default_out_dir_named(&scene.name)
}

/// Runs a cell scene into `opts.out`.
pub fn run(loaded: &LoadedCell, opts: &RunOptions) -> Result<Outcome> {
    let start = Instant::now();
    let scene = &loaded.scene;
    let out = &opts.out;
    let scene_sha = checkpoint::scene_sha256(&scene.to_toml());
    // A resumed run reads its checkpoint before anything in the directory is rewritten.
    let saved = if opts.resume {
        let (ck, path) = checkpoint::load_latest::<CellCheckpoint>(out)?;
        anyhow::ensure!(
            ck.kind == "cell" && ck.scene_sha256 == scene_sha,
            "the checkpoint {} was written for another scene (or other --set overrides) than the one given",
            path.display()
        );
        tracing::info!("resuming {} at step {} (t = {:e} s) from {}", scene.name, ck.restart.stats.steps, ck.restart.t, path.display());
        Some(ck)
    } else {
        None
    };
    let profiles = out.join("profiles");
    std::fs::create_dir_all(&profiles).with_context(|| format!("cannot create {}", profiles.display()))?;
    output::write_atomic(&out.join("scene.resolved.toml"), scene.to_toml().as_bytes())?;
    let model = Model::new(scene);
    let settings = Settings {
        rtol: scene.scheme.rtol,
        atol_concentration: scene.atol_concentration(),
        atol_potential: scene.scheme.atol_potential_v,
        end_time: scene.scheme.end_time_s,
        output_times: scene.output.times_s.clone(),
        max_steps: scene.scheme.max_steps,
        explicit_dt: if scene.scheme.integrator == mscale_cell::scene::Integrator::ExplicitEuler { scene.scheme.timestep_s } else { None },
        start: saved.as_ref().map(|c| c.restart.clone()),
        linear_solver: scene.scheme.linear_solver,
    };
    let y_init = model.initial_state();
    if let Some(r) = &settings.start {
        check_restart(r, &model, &settings, &y_init).with_context(|| format!("cannot resume from the checkpoint in {}", out.display()))?;
    }
    let end = settings.end_time;
    let bar = crate::run::progress_bar(opts.progress_bar, 1000, end);
    let mut last_log = Instant::now();
    let mut write_error: Option<anyhow::Error> = None;
    // The newest restart point (written when the run is stopped) and the step of the last
    // checkpoint written.
    let mut newest: Option<CellCheckpoint> = saved.clone();
    let mut profile_index = saved.map(|c| c.profile_index).unwrap_or_default();
    let mut output_s = 0.0;
    let mut checkpointed_at = settings.start.as_ref().map_or(0, |r| r.stats.steps);
    let mut cancelled: Option<(PathBuf, u64)> = None;
    let setup_s = start.elapsed().as_secs_f64();
    let first_step = checkpointed_at;
    // Progress for the job service (steps to go are unknown: adaptive steps).
    let progress = |step: u64, t: f64, done: bool| Progress {
        step,
        steps: 0,
        time: t,
        end_time: end,
        elapsed_s: start.elapsed().as_secs_f64(),
        session_steps: step - first_step,
        energy_drift: 0.0,
        done,
    };
    let result = {
        let mut on_snapshot = |s: &Snapshot<'_>| -> Control {
            if s.output {
                let t0 = Instant::now();
                let stem = format!("profile_{}", s.step);
                if let Err(e) = write_profile(&model, s.y, s.t, &profiles, &stem, scene.output.plots) {
                    write_error = Some(e);
                    return Control::Stop;
                }
                profile_index.push(format!("{},{:e},profiles/{stem}.csv", s.step, s.t));
                output_s += t0.elapsed().as_secs_f64();
            }
            if let Some(r) = s.restart {
                let ck = CellCheckpoint {
                    kind: "cell".into(),
                    scene_sha256: scene_sha.clone(),
                    restart: r.clone(),
                    profile_index: profile_index.clone(),
                };
                if opts.checkpoint_every > 0 && s.step >= checkpointed_at + opts.checkpoint_every {
                    if let Err(e) = checkpoint::write(out, &ck) {
                        write_error = Some(e);
                        return Control::Stop;
                    }
                    checkpointed_at = s.step;
                }
                newest = Some(ck);
            }
            if let Some(p) = &opts.progress {
                p(&progress(s.step, s.t, false));
            }
            let permille = ((s.t / end) * 1000.0).clamp(0.0, 1000.0) as u64;
            if let Some(b) = &bar {
                b.set_position(permille);
                b.set_message(format!("t = {:.3e} / {end:e} s, step {}", s.t, s.step));
            } else if last_log.elapsed().as_secs_f64() > 10.0 {
                last_log = Instant::now();
                tracing::info!("step {} t = {:.4e} / {end:e} s", s.step, s.t);
            }
            if opts.cancel.as_ref().is_some_and(|c| c.load(Ordering::SeqCst)) {
                if let Some(ck) = &newest {
                    match checkpoint::write(out, ck) {
                        Ok(path) => cancelled = Some((path, ck.restart.stats.steps)),
                        Err(e) => write_error = Some(e),
                    }
                }
                return Control::Stop;
            }
            Control::Continue
        };
        solver::integrate(&model, &settings, &mut on_snapshot)
    };
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    if let Some(e) = write_error {
        return Err(e);
    }
    if let Some((checkpoint, step)) = cancelled {
        return Ok(Outcome::Cancelled { checkpoint, step });
    }
    let wall = start.elapsed().as_secs_f64();
    let (y, status, failure, stats) = match result {
        Ok((y, _open, stats)) => {
            let status = if stats.stopped { "cancelled" } else { "completed" };
            (y, status, None, stats)
        }
        Err(e) => (y_init.clone(), "failed", Some(e.to_string()), Stats::default()),
    };
    let t_out = Instant::now();
    write_profile(&model, &y, stats.t, &profiles, "profile_final", scene.output.plots)?;
    let mut index = String::from("step,time_s,file\n");
    for l in &profile_index {
        index.push_str(l);
        index.push('\n');
    }
    output::write_atomic(&profiles.join("index.csv"), index.as_bytes())?;
    output_s += t_out.elapsed().as_secs_f64();
    let summary = summary_json(loaded, opts, &model, &y_init, &y, &stats, status, failure.as_deref(), wall, setup_s, output_s)?;
    output::write_atomic(&out.join("summary.json"), serde_json::to_string_pretty(&summary)?.as_bytes())?;
    if let Some(p) = &opts.progress {
        p(&progress(stats.steps, stats.t, true));
    }
    Ok(match (failure, stats.stopped) {
        (Some(why), _) => Outcome::Failed(summary, why),
        (None, true) => Outcome::Failed(summary, "stopped on request before its first restart point".into()),
        (None, false) => Outcome::Completed(summary),
    })
}

#[allow(clippy::too_many_arguments)]
fn summary_json(
    loaded: &LoadedCell,
    opts: &RunOptions,
    model: &Model,
    y_init: &[f64],
    y: &[f64],
    stats: &Stats,
    status: &str,
    failure: Option<&str>,
    wall: f64,
    setup_s: f64,
    output_s: f64,
) -> Result<Value> {
    let scene = &loaded.scene;
    let (t0, t1) = (model.totals(y_init), model.totals(y));
    let rel = |a: f64, b: f64| finite_or_null((b - a).abs() / a.abs().max(1.0));
    let (gauss_lhs, gauss_q, field0) = model.gauss(y, &[]);
    let mut inputs = serde_json::Map::new();
    inputs.insert(loaded.path.display().to_string(), json!(output::sha256_file(&loaded.path)?));
    let solver_s = stats.wall_s;
    let other = (solver_s - stats.rhs_s - stats.jacobian_s - stats.lu_factor_s - stats.lu_solve_s).max(0.0);
    // The rhs inside the Jacobian's differences is counted as Jacobian time.
    Ok(json!({
        "status": status,
        "error": failure,
        "scene": scene.name,
        "kind": "cell",
        "wall_seconds": wall,
        "steps": stats.steps,
        "simulated_time_s": stats.t,
        "end_time_s": scene.scheme.end_time_s,
        "cells": model.n,
        "unknowns": model.len(),
        "dx_nm": model.dx,
        "integrator": if scene.scheme.integrator == mscale_cell::scene::Integrator::Bdf { if scene.scheme.linear_solver == mscale_cell::scene::LinearSolver::Banded { "diffsol BDF (variable order 1-5), banded LU" } else { "diffsol BDF (variable order 1-5), faer sparse LU" } } else { "explicit Euler" },
        "face_state": scene.scheme.face_state,
        "totals": {
            "initial": totals_json(model, y_init),
            "final": totals_json(model, y),
        },
        "conservation": {
            "cation_drift": rel(t0.cations, t1.cations),
            "electron_drift": rel(t0.electrons, t1.electrons),
            "max_cation_drift": finite_or_null(stats.max_cation_drift),
            "max_electron_drift": finite_or_null(stats.max_electron_drift),
        },
        "checks": {
            "max_poisson_residual_relative": finite_or_null(stats.max_poisson_residual),
            "max_gauss_error_relative": finite_or_null(stats.max_gauss_error),
            "gauss_final": { "eps0_over_e_times_field_jump": finite_or_null(gauss_lhs), "net_charge": finite_or_null(gauss_q), "field_at_x0_v_per_nm": finite_or_null(field0) },
            "min_p_per_nm3": finite_or_null(stats.min_p),
        },
        "step_statistics": {
            "accepted_steps": stats.steps,
            "error_test_failures": stats.error_test_failures,
            "newton_iterations": stats.newton_iterations,
            "newton_failures": stats.newton_failures,
            "lu_setups": stats.lu_setups,
            "jacobian_evaluations": stats.jacobian_evaluations,
            "rhs_evaluations": stats.rhs_evaluations,
            "switch_events": stats.switch_events,
            "switches": stats.switch_log.iter().map(|(t, k, open)| json!({"t_s": t, "interface": k, "open": open})).take(200).collect::<Vec<_>>(),
            "min_step_s": finite_or_null(stats.min_step),
            "max_step_s": finite_or_null(stats.max_step),
        },
        "time_breakdown_s": {
            "setup": setup_s,
            "solver": solver_s,
            "rhs": stats.rhs_s - 0.0,
            "jacobian": stats.jacobian_s,
            "lu_factorisation": stats.lu_factor_s,
            "lu_solve": stats.lu_solve_s,
            "solver_other": other,
            "output": output_s,
        },
        "provenance": {
            "program": "mscale",
            "version": env!("CARGO_PKG_VERSION"),
            "commit": option_env!("MSCALE_COMMIT").unwrap_or("unknown"),
            "precision": "f64",
            "inputs": inputs,
        },
        "command_line": opts.command_line,
        "state_digest": mscale_cell::state_digest(stats.steps, stats.t, y),
    }))
}

/// The cumulative charge of a profile (rows x_nm, p, n, phi, p - n of a uniform grid) at its
/// faces: (0, 0), then (x_i + dx/2, sum_{j <= i} (p - n)_j dx).
fn cumulative_charge(prof: &[[f64; 5]]) -> Vec<(f64, f64)> {
    let dx = match prof {
        [a, b, ..] => b[0] - a[0],
        [a] => 2.0 * a[0],
        [] => return vec![(0.0, 0.0)],
    };
    let mut q = 0.0;
    std::iter::once((0.0, 0.0))
        .chain(prof.iter().map(|r| {
            q += r[4] * dx;
            (r[0] + 0.5 * dx, q)
        }))
        .collect()
}

/// `mscale report error-vs-time` of a cell scene: one run per combination of the sweeps; the
/// error of each run is the thesis's (8.85), sqrt(sum (f_i - f(x_i))^2 / N), of phi and of
/// p - n at the final time against the run with the most cells (interpolated linearly to the
/// run's cell centres), and of the cumulative charge sum (p - n) dx left of each of the run's
/// faces (interpolated linearly between the finest run's faces). p - n next to an interface
/// does not converge (the electrodes' electrons store their charge in one cell, whose p - n
/// grows as 1/dx; cell/README.md, the refinement study); the cumulative charge, eps0/e times the field,
/// does. Writes report.csv and report.png (error against cells).
pub fn error_vs_time(scene_path: &Path, sets: &[String], sweeps: &[Sweep], out: &Path) -> Result<usize, report::ReportError> {
    let combos = report::combinations(sweeps);
    let mut runs = Vec::new();
    for (k, combo) in combos.iter().enumerate() {
        let mut all = sets.to_vec();
        all.extend(combo.iter().cloned());
        let loaded = load(scene_path, &all).map_err(report::ReportError::Scene)?;
        let dir = out.join(format!("run{k}"));
        let mut opts = RunOptions::new(dir.clone(), vec!["mscale".into(), "report".into()]);
        opts.progress_bar = false;
        let summary = match run(&loaded, &opts).map_err(report::ReportError::Io)? {
            Outcome::Completed(s) => s,
            Outcome::Failed(_, why) => return Err(report::ReportError::Io(anyhow::anyhow!("run {k} ({}) failed: {why}", combo.join(" ")))),
            Outcome::Cancelled { .. } => return Err(report::ReportError::Io(anyhow::anyhow!("run {k} cancelled"))),
        };
        let rows = report::read_csv(&dir.join("profiles/profile_final.csv")).map_err(report::ReportError::Io)?;
        let prof: Vec<[f64; 5]> = rows
            .iter()
            .skip(1)
            .map(|r| {
                let mut v = [0.0; 5];
                for (i, x) in r.iter().take(5).enumerate() {
                    v[i] = x.parse().unwrap_or(f64::NAN);
                }
                v
            })
            .collect();
        runs.push((combo.join(" "), summary, prof));
    }
    let finest = runs.iter().enumerate().max_by_key(|(_, r)| r.1["cells"].as_u64().unwrap_or(0)).map(|(i, _)| i).unwrap_or(0);
    let reference = &runs[finest].2;
    let column = |col: usize| -> Vec<(f64, f64)> { reference.iter().map(|r| (r[0], r[col])).collect() };
    let (ref_phi, ref_charge, ref_cumulative) = (column(3), column(4), cumulative_charge(reference));
    let mut csv = String::from(
        "run,settings,cells,wall_seconds,steps,phi_l2_error_v,charge_l2_error_e_per_nm3,cumulative_charge_l2_error_e_per_nm2\n",
    );
    let (mut phi_series, mut charge_series, mut cumulative_series) = (Vec::new(), Vec::new(), Vec::new());
    for (k, (settings, summary, prof)) in runs.iter().enumerate() {
        let l2 = |pairs: &mut dyn Iterator<Item = (f64, f64)>| {
            let (sum, count) = pairs.fold((0.0, 0usize), |(s, c), (x, v)| (s + (v - x).powi(2), c + 1));
            (sum / count.max(1) as f64).sqrt()
        };
        let err = |col: usize, reference: &[(f64, f64)]| l2(&mut prof.iter().map(|r| (report::interpolate(reference, r[0]), r[col])));
        let (e_phi, e_q, e_cum) = if k == finest {
            (f64::NAN, f64::NAN, f64::NAN)
        } else {
            // The run's faces right of x = 0 (the cumulative charge there is 0 in every run).
            let e_cum = l2(&mut cumulative_charge(prof).into_iter().skip(1).map(|(x, q)| (report::interpolate(&ref_cumulative, x), q)));
            (err(3, &ref_phi), err(4, &ref_charge), e_cum)
        };
        let cells = summary["cells"].as_u64().unwrap_or(0);
        let cell = |e: f64| if e.is_finite() { format!("{e:e}") } else { "reference".into() };
        csv.push_str(&format!(
            "{k},{settings},{cells},{},{},{},{},{}\n",
            summary["wall_seconds"].as_f64().unwrap_or(f64::NAN),
            summary["steps"],
            cell(e_phi),
            cell(e_q),
            cell(e_cum),
        ));
        for (series, e) in [(&mut phi_series, e_phi), (&mut charge_series, e_q), (&mut cumulative_series, e_cum)] {
            if e.is_finite() && e > 0.0 {
                series.push((cells as f64, e));
            }
        }
    }
    output::write_atomic(&out.join("report.csv"), csv.as_bytes()).map_err(report::ReportError::Io)?;
    output::plot_loglog(
        &out.join("report.png"),
        "L2 error (8.85) against the finest run",
        "cells",
        "error",
        &[
            Series { label: "phi (V)", points: phi_series, line: true },
            Series { label: "p - n (e/nm^3)", points: charge_series, line: true },
            Series { label: "cumulative charge (e/nm^2)", points: cumulative_series, line: true },
        ],
    )
    .map_err(report::ReportError::Io)?;
    Ok(runs.len())
}
