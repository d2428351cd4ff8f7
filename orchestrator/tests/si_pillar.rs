//! Issue 19: the silicon pillar (scenes/si-pillar-2d.toml), a short run at the faster flux
//! (j = 1e-8): lithium enters only through the pillar's free faces (side and top: 150 nm per
//! unit depth, not the symmetry plane nor the face on the substrate), is conserved to round-off
//! against that surface source, stays out of the substrate, swells the surface layer, which the
//! core and the substrate hold back: the lithiated shell is in compression and yields; the VTK
//! snapshots carry concentration, pressure and plastic strain.

use orchestrator::run::{Outcome, RunOptions, run};
use orchestrator::scene;
use serde_json::Value;
use std::path::Path;

#[test]
fn the_pillar_takes_lithium_through_its_free_surface_and_its_shell_is_compressed() {
    let (flux, end) = (1e-8, 0.6);
    let sets: Vec<String> = [
        format!("diffusion.surface_flux={flux}"),
        format!("scheme.end_time={end}"),
        "output.snapshots=1".into(),
        "output.plots=false".into(),
    ]
    .into();
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/si-pillar-2d.toml");
    let loaded = scene::load(&path, &sets).expect("scene loads");
    let dir = tempfile::tempdir().expect("temp dir");
    let s: Value = match run(&loaded, &RunOptions::new(dir.path().to_path_buf(), Vec::new())).expect("run") {
        Outcome::Completed(s) => s,
        Outcome::Failed(_, e) => panic!("pillar: {e}"),
        Outcome::Cancelled { .. } => panic!("not cancelled"),
    };
    let f = |a: &str, b: &str| s[a][b].as_f64().unwrap_or_else(|| panic!("{a}.{b} in {s}"));
    let time = s["simulated_time_s"].as_f64().expect("time");
    // Conservation: the content changes by exactly what the surface let in.
    let (inflow, change) = (f("diffusion", "boundary_content"), f("diffusion", "content_change"));
    eprintln!("content change {change:e}, surface source {inflow:e}, error {:e}", f("diffusion", "conservation_error"));
    // Round-off: each step's nodal fluxes cancel to a few ulps of their own size, which is
    // far above the net inflow; 2400 steps of that measured 2.9e-12 of the inflow.
    assert!(f("diffusion", "relative_conservation_error").abs() < 1e-10, "{}", s["diffusion"]);
    // The exposed area is the side (100 nm) and the top (50 nm): the inflow is j A t times the
    // saturation factor, which is 1 at c = 0 and falls as the surface fills.
    let full = flux * 1.5e-7 * time;
    eprintln!("inflow / (j A t) = {:.4}", inflow / full);
    assert!(inflow <= full * (1.0 + 1e-12) && inflow > 0.7 * full, "inflow {inflow:e} against j A t = {full:e}");
    // The particle file: the substrate holds no lithium, the shell is compressed and yields.
    let csv = std::fs::read_to_string(dir.path().join("particles_final.csv")).expect("particles_final.csv");
    let mut lines = csv.lines();
    let head: Vec<&str> = lines.next().expect("header").split(',').collect();
    let col = |name: &str| head.iter().position(|h| *h == name).unwrap_or_else(|| panic!("no column {name} in {head:?}"));
    let (y0, c, p, ep, vol) = (col("y0"), col("concentration"), col("pressure"), col("plastic_strain"), col("volume"));
    let rows: Vec<Vec<f64>> = lines.map(|l| l.split(',').map(|v| v.parse().unwrap_or(f64::NAN)).collect()).collect();
    let substrate: Vec<&Vec<f64>> = rows.iter().filter(|r| r[y0] < 2.5e-8).collect();
    let pillar: Vec<&Vec<f64>> = rows.iter().filter(|r| r[y0] > 2.5e-8).collect();
    assert_eq!(substrate.len() + pillar.len(), rows.len());
    assert!(substrate.iter().all(|r| r[c] == 0.0), "lithium in the substrate");
    let mean = |set: &[&&Vec<f64>], k: usize| {
        let w: f64 = set.iter().map(|r| r[vol]).sum();
        set.iter().map(|r| r[k] * r[vol]).sum::<f64>() / w
    };
    let shell: Vec<&&Vec<f64>> = pillar.iter().filter(|r| r[c] > 0.1).collect();
    let core: Vec<&&Vec<f64>> = pillar.iter().filter(|r| r[c] < 0.01).collect();
    let c_max = pillar.iter().map(|r| r[c]).fold(0.0, f64::max);
    let yielded = pillar.iter().filter(|r| r[ep] > 0.0).count();
    eprintln!(
        "t = {time} s: c_max {c_max:.3}, shell {} points, mean p {:.3e} Pa, core {} points, mean p {:.3e} Pa; {yielded} pillar points yielded, KE/elastic {:e}",
        shell.len(),
        mean(&shell, p),
        core.len(),
        mean(&core, p),
        f("quasi_static", "final_kinetic_over_elastic")
    );
    assert!(shell.len() > 20 && core.len() > 20, "a shell and a core: {} and {}", shell.len(), core.len());
    assert!(mean(&shell, p) > 5e8, "the lithiated shell is in compression: {:e}", mean(&shell, p));
    assert!(mean(&core, p) < -1e8, "the swelling shell holds the core in tension: {:e}", mean(&core, p));
    assert!(yielded > 0 && mean(&shell, ep) > 0.0, "the shell yields");
    // The VTK snapshot names the fields.
    let vtk = std::fs::read_dir(dir.path().join("vtk"))
        .expect("vtk/")
        .filter_map(|e| e.ok())
        .find(|e| e.path().extension().is_some_and(|x| x == "vtu"))
        .expect("a .vtu snapshot");
    let text = std::fs::read_to_string(vtk.path()).expect("vtu");
    for name in ["concentration", "pressure", "plastic_strain", "body"] {
        assert!(text.contains(&format!("Name=\"{name}\"")), "{name} missing from {}", vtk.path().display());
    }
}
