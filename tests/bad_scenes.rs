//! Every bad scene is refused before anything runs, with a message that names the file, the
//! line (or the --set), the key, the value and what is allowed.

use mscale_tests::{repo, small_scene};
use orchestrator::scene;

/// Parses the small scene after replacing `from` with `to` (which must occur) and applying `sets`.
fn parse_edited(from: &str, to: &str, sets: &[&str]) -> Result<scene::LoadedScene, scene::SceneError> {
    let base = small_scene();
    assert!(from.is_empty() || base.contains(from), "test bug: `{from}` is not in the small scene");
    let text = if from.is_empty() { base } else { base.replacen(from, to, 1) };
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    scene::parse("bad.toml", &text, &sets, &repo().join("scenes"), "bad")
}

/// (what, replace this, with this, overrides, every fragment the message must contain)
const CASES: &[(&str, &str, &str, &[&str], &[&str])] = &[
    ("unknown top-level key", "name = \"small\"", "name = \"small\"\ncolour = 3", &[], &["bad.toml", "line 3", "unknown field `colour`"]),
    (
        "unknown key in a body",
        "density = 1.0\n",
        "density = 1.0\ndensty = 2.0\n",
        &[],
        &["line 22", "`densty`", "unknown field `densty`", "expected one of"],
    ),
    ("missing scheme", "[scheme]\nmethod", "[schemex]\nmethod", &[], &["unknown field `schemex`"]),
    ("missing end time", "end_time = 0.1\n", "\n", &[], &["missing field `end_time`"]),
    ("wrong type", "cells = [50]", "cells = \"fifty\"", &[], &["line 8", "invalid type: string \"fifty\""]),
    ("schema version", "schema = 1", "schema = 7", &[], &["line 1", "`schema` = 7", "this build reads schema 1"]),
    ("dimension 4", "dimension = 1", "dimension = 4", &[], &["line 5", "`domain.dimension` = 4", "allowed: 1, 2 or 3"]),
    ("inverted domain", "max = [1.0]\ncells", "max = [-1.0]\ncells", &[], &["line 7", "`domain.max` = [-1.0]", "must exceed domain.min"]),
    (
        "cells and cell_size disagree",
        "cells = [50]",
        "cells = [50]\ncell_size = [0.03]",
        &[],
        &["line 9", "`domain.cell_size` = [0.03]", "disagrees with cells = [50]"],
    ),
    ("zero cells", "cells = [50]", "cells = [0]", &[], &["`domain.cells` = [0]", "positive integer"]),
    ("cell size not dividing", "cells = [50]", "cell_size = [0.3]", &[], &["`domain.cell_size` = [0.3]", "whole number of cells"]),
    ("negative density", "density = 1.0\n", "density = -1.0\n", &[], &["line 21", "`bodies.right.density` = -1", "finite positive"]),
    (
        "body outside the domain",
        "max = [1.0]\ndensity = 1.0",
        "max = [1.5]\ndensity = 1.0",
        &[],
        &["`bodies.right.max`", "inside the domain"],
    ),
    (
        "unknown law",
        "law = \"ideal-gas-isothermal\", sound_speed = 1.0 }\n\n[bodies.right]",
        "law = \"unobtainium\", sound_speed = 1.0 }\n\n[bodies.right]",
        &[],
        &["unknown variant `unobtainium`", "ideal-gas-isothermal"],
    ),
    (
        "zero sound speed",
        "sound_speed = 1.0 }\n\n[scheme]",
        "sound_speed = 0.0 }\n\n[scheme]",
        &[],
        &["`bodies.right.material.sound_speed` = 0", "finite positive"],
    ),
    ("unknown method", "method = \"ugimp\"", "method = \"magic\"", &[], &["line 25", "`scheme.method` = \"magic\"", "allowed: mpm, ugimp"]),
    ("CFL beyond stability", "cfl = 0.2", "cfl = 1.5", &[], &["line 28", "`scheme.cfl` = 1.5", "0 < cfl <= 1"]),
    (
        "time step beyond the bound",
        "cfl = 0.2",
        "timestep = 0.05",
        &[],
        &["`scheme.timestep` = 0.05", "exceeds the stability bound", "2.000000e-2 s"],
    ),
    (
        "cfl and timestep disagree",
        "cfl = 0.2",
        "cfl = 0.2\ntimestep = 0.001",
        &[],
        &["`scheme.timestep` = 0.001", "disagrees with cfl = 0.2", "not both"],
    ),
    ("no time step", "cfl = 0.2\n", "\n", &[], &["`scheme`", "missing `cfl`"]),
    ("negative end time", "end_time = 0.1", "end_time = -0.1", &[], &["`scheme.end_time` = -0.1"]),
    (
        "unknown boundary",
        "x_min = \"reflective\"",
        "x_min = \"sticky\"",
        &[],
        &["line 32", "`boundary.x_min` = \"sticky\"", "allowed: \"free\", \"fixed\""],
    ),
    ("half periodic", "x_min = \"reflective\"", "x_min = \"periodic\"", &[], &["`boundary.x_max`", "periodic must be set on both"]),
    (
        "face of a missing axis",
        "x_max = \"reflective\"",
        "x_max = \"reflective\"\ny_min = \"fixed\"",
        &[],
        &["`boundary.y_min` = \"fixed\"", "a 1D scene has no y_min face"],
    ),
    (
        "reference names a missing body",
        "right = \"right\"\n",
        "right = \"middle\"\n",
        &[],
        &["`reference.right` = \"middle\"", "no such body; bodies: left, right"],
    ),
    (
        "too many particles per cell",
        "particles_per_cell = 4",
        "particles_per_cell = 0",
        &[],
        &["`scheme.particles_per_cell` = 0", "allowed: 1 to 64"],
    ),
    (
        "unknown gradient correction",
        "",
        "",
        &["scheme.gradient_correction=\"quadratic\""],
        &["`scheme.gradient_correction` = \"quadratic\"", "\"none\", \"constant\", \"linear\""],
    ),
    (
        "gradient correction on ddmp",
        "",
        "",
        &["scheme.method=\"ddmp\"", "scheme.gradient_correction=\"linear\""],
        &["`scheme.gradient_correction` = \"linear\"", "`ddmp` has its own gradient", "apply to mpm, ugimp"],
    ),
    (
        "gradient correction with the implicit integrator",
        "",
        "",
        &["scheme.method=\"mpm\"", "scheme.integrator=\"implicit-trapezoidal\"", "scheme.gradient_correction=\"constant\""],
        &["`scheme.gradient_correction` = \"constant\"", "the implicit integrator assembles its own forces"],
    ),
    (
        "unknown nullspace filter",
        "",
        "",
        &["scheme.nullspace_filter=\"svd\""],
        &["`scheme.nullspace_filter` = \"svd\"", "\"none\", \"local\", \"global-svd\""],
    ),
    (
        "nullspace filter on impm",
        "",
        "",
        &["scheme.method=\"impm\"", "scheme.integrator=\"leapfrog\"", "scheme.nullspace_filter=\"local\""],
        &["`scheme.nullspace_filter` = \"local\"", "`impm` maps velocities to the nodes by MLS", "apply to mpm, ugimp"],
    ),
    (
        "nullspace filter with the implicit integrator",
        "",
        "",
        &["scheme.method=\"mpm\"", "scheme.integrator=\"implicit-trapezoidal\"", "scheme.nullspace_filter=\"global-svd\""],
        &["`scheme.nullspace_filter` = \"global-svd\"", "the implicit integrator computes its velocity gradients"],
    ),
    (
        "global SVD filter on too many points",
        "",
        "",
        &["scheme.particles_per_cell=41", "scheme.nullspace_filter=\"global-svd\""],
        &["`scheme.nullspace_filter` = \"global-svd\"", "at most 2000 points", "= 2050: use \"local\""],
    ),
    ("bad override value", "", "", &["bodies.left.density=-3"], &["--set bodies.left.density=-3", "`bodies.left.density` = -3"]),
    ("override of an unknown key", "", "", &["scheme.colour=blue"], &["unknown field `colour`"]),
    ("override through a value", "", "", &["scheme.method.name=x"], &["--set scheme.method.name=x", "is a value, not a table"]),
    ("malformed override", "", "", &["scheme.cfl"], &["--set scheme.cfl", "expected --set dotted.key=value"]),
    ("not TOML", "[domain]", "[domain", &[], &["not valid TOML"]),
    (
        "missing potential file",
        "material = { law = \"ideal-gas-isothermal\", sound_speed = 1.0 }\n\n[bodies.right]",
        "material = { law = \"md\", potential = \"nowhere/Cu.eam.alloy\", lattice = \"fcc\", lattice_constant_angstrom = 3.615, cells_per_side = 5 }\n\n[bodies.right]",
        &[],
        &["line 15", "`bodies.left.material.potential` = \"nowhere/Cu.eam.alloy\"", "no such file", "relative to the scene file"],
    ),
    (
        "skewed crystal orientation",
        "material = { law = \"ideal-gas-isothermal\", sound_speed = 1.0 }\n\n[bodies.right]",
        "material = { law = \"md\", potential = \"../md-worker/potentials/Cu_mishin1.eam.alloy\", lattice = \"fcc\", lattice_constant_angstrom = 3.615, cells_per_side = 5, orientation = [[1, 1, 0], [1, 0, 0], [0, 0, 1]] }\n\n[bodies.right]",
        &[],
        &["line 15", "`bodies.left.material.orientation` = [[1, 1, 0], [1, 0, 0], [0, 0, 1]]", "not orthogonal"],
    ),
    (
        "oriented box too large",
        "material = { law = \"ideal-gas-isothermal\", sound_speed = 1.0 }\n\n[bodies.right]",
        "material = { law = \"md\", potential = \"../md-worker/potentials/Cu_mishin1.eam.alloy\", lattice = \"fcc\", lattice_constant_angstrom = 3.615, cells_per_side = 40, orientation = [[1, 1, 1], [-1, 1, 0], [-1, -1, 2]] }\n\n[bodies.right]",
        &[],
        &["`bodies.left.material.cells_per_side` = 40", "1536000 atoms per box", "at most 256000"],
    ),
    (
        "absurd lattice constant",
        "material = { law = \"ideal-gas-isothermal\", sound_speed = 1.0 }\n\n[bodies.right]",
        "material = { law = \"md\", potential = \"../md-worker/potentials/Cu_mishin1.eam.alloy\", lattice = \"fcc\", lattice_constant_angstrom = 1e308, cells_per_side = 5 }\n\n[bodies.right]",
        &[],
        &["line 15", "`bodies.left.material.lattice_constant_angstrom` = 1e308", "at most 100 A"],
    ),
];

#[test]
fn every_bad_scene_is_refused_with_its_message() {
    assert!(CASES.len() >= 20);
    let mut failures = Vec::new();
    for (what, from, to, sets, fragments) in CASES {
        match parse_edited(from, to, sets) {
            Ok(_) => failures.push(format!("{what}: accepted")),
            Err(e) => {
                let msg = e.to_string();
                for f in *fragments {
                    if !msg.contains(f) {
                        failures.push(format!("{what}: message lacks `{f}`:\n    {msg}"));
                    }
                }
            }
        }
    }
    assert!(failures.is_empty(), "{} of {} cases failed:\n{}", failures.len(), CASES.len(), failures.join("\n"));
}

#[test]
fn the_small_scene_is_valid_and_overrides_apply() {
    let loaded = parse_edited("", "", &["bodies.left.temperature_k=250", "scheme.particles_per_cell=2"]).expect("valid");
    assert_eq!(loaded.scene.bodies["left"].temperature_k, 250.0);
    assert_eq!(loaded.scene.scheme.particles_per_cell, 2);
    // Defaults are filled: the time step comes from the CFL number (0.2 * 0.02 m / 1 m/s).
    assert!((loaded.dt - 0.004).abs() < 1e-15);
    assert_eq!(loaded.steps, 25);
    assert_eq!(loaded.scene.scheme.timestep, Some(loaded.dt));
    assert_eq!(loaded.scene.domain.cell_size, vec![0.02]);
    // The resolved scene reads back to the same scene.
    let again = scene::parse("resolved.toml", &loaded.scene.to_toml(), &[], &repo(), "x").expect("resolved scene is valid");
    assert_eq!(again.scene, loaded.scene);
}

#[test]
fn shipped_scenes_are_valid() {
    for entry in std::fs::read_dir(repo().join("scenes")).expect("scenes/") {
        let path = entry.expect("entry").path();
        if path.extension().is_none_or(|e| e != "toml") {
            continue;
        }
        // A cell scene (`kind = "cell"`) has its own typed scene, read as `mscale run` reads it.
        let checked = if orchestrator::cell_run::is_cell_scene(&path) {
            orchestrator::cell_run::load(&path, &[]).map(drop)
        } else {
            scene::load(&path, &[]).map(drop)
        };
        if let Err(e) = checked {
            panic!("{} is invalid: {e}", path.display());
        }
    }
}

/// The small scene's `[reference]` replaced by a direct-MD one (`profile` relative to scenes/).
const RIEMANN: &str = "solution = \"isothermal-riemann\"\nleft = \"left\"\nright = \"right\"\n";

/// (what, the direct-md reference's lines, overrides, every fragment the message must contain)
const DIRECT_MD_CASES: &[(&str, &str, &[&str], &[&str])] = &[
    (
        "direct-md profile missing",
        "solution = \"direct-md\"\nprofile = \"nowhere/bar.csv\"\ntimes_ps = [5.0]\n",
        &[],
        &[
            "bad.toml",
            "line 40",
            "`reference.profile` = \"nowhere/bar.csv\"",
            "cannot read the direct-MD reference",
            "relative to the scene file",
        ],
    ),
    (
        "direct-md profile unreadable",
        "solution = \"direct-md\"\nprofile = \"cu-shock-1d.toml\"\ntimes_ps = [5.0]\n",
        &[],
        &["line 40", "`reference.profile` = \"cu-shock-1d.toml\"", "no column `time_ps`", "md-worker direct --slab"],
    ),
    (
        "direct-md time outside the profile",
        "solution = \"direct-md\"\nprofile = \"../tests/golden/cu-shock-1d/direct-bar.csv\"\ntimes_ps = [5.0, 12.5]\n",
        &[],
        &["line 41", "`reference.times_ps[1]` = 12.5", "outside the profile's range 0 to 10 ps"],
    ),
    (
        "direct-md time between frames",
        "solution = \"direct-md\"\nprofile = \"../tests/golden/cu-shock-1d/direct-bar.csv\"\ntimes_ps = [7.25]\n",
        &[],
        &["`reference.times_ps[0]` = 7.25", "no frame at t = 7.25 ps", "0, 0.5, 1"],
    ),
    (
        "direct-md time after the end",
        "solution = \"direct-md\"\nprofile = \"../tests/golden/cu-shock-1d/direct-bar.csv\"\ntimes_ps = [5.0]\n",
        &["scheme.end_time=4e-12"],
        &["`reference.times_ps[0]` = 5", "after the end time 4 ps"],
    ),
    (
        "direct-md no times",
        "solution = \"direct-md\"\nprofile = \"../tests/golden/cu-shock-1d/direct-bar.csv\"\ntimes_ps = []\n",
        &[],
        &["`reference.times_ps` = []", "at least one time"],
    ),
    (
        "direct-md unknown component",
        "solution = \"direct-md\"\nprofile = \"../tests/golden/cu-shock-1d/direct-bar.csv\"\ntimes_ps = [5.0]\ncomponent = \"sxy\"\n",
        &[],
        &["line 42", "`reference.component` = \"sxy\"", "allowed: \"sxx\", \"syy\", \"szz\""],
    ),
    (
        "direct-md without particle files",
        "solution = \"direct-md\"\nprofile = \"../tests/golden/cu-shock-1d/direct-bar.csv\"\ntimes_ps = [5.0]\n",
        &["output.particles=false"],
        &["--set output.particles=false", "`output.particles`", "needs output.particles = true"],
    ),
    ("unknown reference solution", "solution = \"oracle\"\n", &[], &["unknown variant `oracle`", "direct-md"]),
];

#[test]
fn every_bad_direct_md_reference_is_refused_with_its_message() {
    let mut failures = Vec::new();
    for (what, to, sets, fragments) in DIRECT_MD_CASES {
        match parse_edited(RIEMANN, to, sets) {
            Ok(_) => failures.push(format!("{what}: accepted")),
            Err(e) => {
                let msg = e.to_string();
                for f in *fragments {
                    if !msg.contains(f) {
                        failures.push(format!("{what}: message lacks `{f}`:\n    {msg}"));
                    }
                }
            }
        }
    }
    assert!(failures.is_empty(), "{} of {} cases failed:\n{}", failures.len(), DIRECT_MD_CASES.len(), failures.join("\n"));
    // The same reference with valid values is accepted, its profile made absolute and listed
    // among the scene's files.
    let ok = "solution = \"direct-md\"\nprofile = \"../tests/golden/cu-shock-1d/direct-bar.csv\"\ntimes_ps = [5.0, 10.0]\n";
    let loaded = parse_edited(RIEMANN, ok, &[]).expect("valid direct-md reference");
    let Some(scene::Reference::DirectMd(r)) = &loaded.scene.reference else {
        panic!("not a direct-md reference: {:?}", loaded.scene.reference)
    };
    assert!(r.profile.is_absolute() && r.profile.ends_with("tests/golden/cu-shock-1d/direct-bar.csv"), "{}", r.profile.display());
    assert_eq!(r.component, "sxx");
    assert!(loaded.files.contains(&r.profile));
}

#[test]
fn the_global_svd_filter_is_refused_in_2d_and_the_local_one_is_read_back() {
    let path = repo().join("scenes/mms-2d.toml");
    let e = scene::load(&path, &["scheme.nullspace_filter=\"global-svd\"".to_string()]).expect_err("refused").to_string();
    for f in ["`scheme.nullspace_filter` = \"global-svd\"", "for 1D reference runs", "a 2D scene allows \"none\" or \"local\""] {
        assert!(e.contains(f), "message lacks `{f}`: {e}");
    }
    let loaded = scene::load(&path, &["scheme.nullspace_filter=\"local\"".to_string()]).expect("local is allowed in 2D");
    assert_eq!(format!("{:?}", loaded.resolved.nullspace_filter), "Local");
    let text = loaded.scene.to_toml();
    assert!(text.contains("nullspace_filter = \"local\""), "{text}");
    let again = scene::parse("resolved.toml", &text, &[], &repo(), "x").expect("resolved scene is valid");
    assert_eq!(again.scene, loaded.scene);
    // Not written when none (so existing scenes' resolved TOML and digests do not move).
    let plain = scene::load(&path, &[]).expect("valid");
    assert!(!plain.scene.to_toml().contains("nullspace_filter"));
}
