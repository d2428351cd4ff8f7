//! Mutation fuzzing of what a user hands the engine: the three EAM potential formats and
//! LAMMPS data files. Valid inputs are mutated (tokens swapped for hostile numbers, lines
//! dropped, doubled, swapped, bytes changed, truncation), parsed, and what parses is put
//! through the engine (time-step bound, a box built and stepped). No mutation may panic
//! (every error is a value), and every input that once broke the engine is a named
//! regression test below. The streams are deterministic (ChaCha from a fixed seed), so a
//! failure names the seed and iteration that reproduce it. Each target runs a fixed
//! number of mutations (MSCALE_FUZZ_ITERS or MSCALE_FUZZ_SECS change it).
#![allow(clippy::unwrap_used)]

mod common;
use common::*;
use md_worker::data::DataFile;
use md_worker::{BoxResult, BoxSpec, BoxWork, LatticeKind, MdBackend, Potential, ReferenceBackend};
use mscale_testkit::fuzz::Budget;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha20Rng;
use std::sync::Arc;
use std::time::Instant;

/// Numbers and words that broke parsers somewhere.
const HOSTILE: &[&str] = &[
    "nan",
    "NaN",
    "inf",
    "-inf",
    "0",
    "-0",
    "1e308",
    "-1e308",
    "1e-308",
    "5e-324",
    "-1",
    "1",
    "2",
    "5",
    "4294967295",
    "4294967296",
    "18446744073709551615",
    "99999999999999999999",
    "100000000000",
    "0x10",
    "",
    "1e",
    "-",
    "+",
    ".",
    "3.615FCC",
    "1D5",
    "\u{fffd}",
    "atoms",
    "Atoms",
    "Masses",
    "Velocities",
    "xlo",
    "xhi",
];

/// One to three random mutations of `text`; lines near the top (headers) are hit half the time.
fn mutate(rng: &mut ChaCha20Rng, text: &str) -> String {
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for _ in 0..rng.gen_range(1..=3) {
        if lines.is_empty() {
            lines.push(String::new());
        }
        let n = lines.len();
        let at = if rng.gen_bool(0.5) { rng.gen_range(0..n.min(12)) } else { rng.gen_range(0..n) };
        match rng.gen_range(0..8) {
            0 | 1 => {
                // A token replaced by a hostile one.
                let mut w: Vec<String> = lines[at].split_whitespace().map(str::to_string).collect();
                let h = HOSTILE[rng.gen_range(0..HOSTILE.len())].to_string();
                if w.is_empty() {
                    w.push(h);
                } else {
                    let k = rng.gen_range(0..w.len());
                    w[k] = h;
                }
                lines[at] = w.join(" ");
            }
            2 => {
                lines.remove(at);
            }
            3 => {
                let l = lines[at].clone();
                lines.insert(at, l);
            }
            4 => {
                let b = rng.gen_range(0..n);
                lines.swap(at, b);
            }
            5 => {
                // A token dropped or added.
                let mut w: Vec<&str> = lines[at].split_whitespace().collect();
                if !w.is_empty() && rng.gen_bool(0.5) {
                    w.remove(rng.gen_range(0..w.len()));
                } else {
                    w.push(HOSTILE[rng.gen_range(0..HOSTILE.len())]);
                }
                lines[at] = w.join(" ");
            }
            6 => {
                // A byte changed to a random printable character.
                let mut b = lines[at].clone().into_bytes();
                if !b.is_empty() {
                    let k = rng.gen_range(0..b.len());
                    b[k] = rng.gen_range(32u8..127);
                }
                lines[at] = String::from_utf8_lossy(&b).to_string();
            }
            _ => {
                // Truncated after this line, mid-line.
                let keep = rng.gen_range(0..=lines[at].len());
                let mut cut = lines[at].clone();
                cut.truncate(cut.char_indices().map(|(i, _)| i).take_while(|&i| i <= keep).last().unwrap_or(0));
                lines.truncate(at);
                lines.push(cut);
            }
        }
    }
    lines.join("\n") + "\n"
}

/// Runs `check` on `iterations` mutations of the seed inputs (or the environment's
/// [`Budget`]); a panic fails the test with the seed input, iteration and the input text (its
/// start).
fn fuzz(target: &str, seeds: &[(String, String)], iterations: u64, check: impl Fn(&str, &str)) {
    let budget = Budget::from_env(iterations);
    let t0 = Instant::now();
    let mut rng = ChaCha20Rng::seed_from_u64(0x5eed_0000 + target.len() as u64);
    let mut iters = 0u64;
    while budget.more(iters, t0.elapsed()) || iters < 20 {
        let (name, text) = &seeds[iters as usize % seeds.len()];
        let input = mutate(&mut rng, text);
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| check(name, &input)));
        if r.is_err() {
            let head: String = input.chars().take(1500).collect();
            panic!("{target}: iteration {iters} (seed input {name}) panicked; input starts:\n{head}");
        }
        iters += 1;
    }
    eprintln!("{target}: {iters} mutated inputs in {:.1} s, 0 panics", t0.elapsed().as_secs_f64());
}

/// What the engine does with a potential that parsed: the time-step bound, and a small box
/// built, evaluated and stepped (errors are fine, panics and hangs are not).
fn exercise_potential(pot: Potential) {
    let _ = pot.max_time_step();
    let mut b = ReferenceBackend::new(Arc::new(pot));
    let mut s = BoxSpec::lattice(1, LatticeKind::Fcc, 3.615, [1, 1, 1]);
    s.temperature_k = 300.0;
    if b.open(&[s]).is_ok() {
        let mut out = [BoxResult::default()];
        let _ = b.step(&[BoxWork::new(1, [[0.01, 0.0, 0.0], [0.0; 3], [0.0; 3]], 3, 0.001)], &mut out);
    }
}

/// A small EAM table set on `nrho` x `nr` grids (Johnson-like analytic functions).
fn tables(nrho: usize, nr: usize) -> (f64, f64, f64, Vec<f64>, Vec<f64>, Vec<f64>) {
    let (drho, dr, cut) = (0.05, 0.03, 5.0);
    let f: Vec<f64> = (0..nrho).map(|k| -(k as f64 * drho).sqrt()).collect();
    let rho: Vec<f64> = (0..nr)
        .map(|k| {
            let r = k as f64 * dr;
            if r < cut { (-3.0 * (r / 2.55 - 1.0)).exp() * (1.0 - r / cut).powi(2) } else { 0.0 }
        })
        .collect();
    let rphi: Vec<f64> = (0..nr)
        .map(|k| {
            let r = k as f64 * dr;
            if r < cut { r * 0.5 * (-6.0 * (r / 2.55 - 1.0)).exp() * (1.0 - r / cut).powi(2) } else { 0.0 }
        })
        .collect();
    (drho, dr, cut, f, rho, rphi)
}

fn block(v: &[f64]) -> String {
    v.chunks(5).map(|c| c.iter().map(|x| format!("{x:.10e}")).collect::<Vec<_>>().join(" ")).collect::<Vec<_>>().join("\n") + "\n"
}

/// Small valid files of the three formats: funcfl, setfl (2 elements), Finnis-Sinclair (2).
fn small_potentials() -> Vec<(String, String)> {
    let (nrho, nr) = (60, 200);
    let (drho, dr, cut, f, rho, rphi) = tables(nrho, nr);
    // funcfl stores Z(r) with r phi = 27.2 * 0.529 * Z^2.
    let z: Vec<f64> = rphi.iter().map(|v| (v.max(0.0) / (27.2 * 0.529)).sqrt()).collect();
    let funcfl = format!("small funcfl\n29 63.55 3.615 FCC\n{nrho} {drho} {nr} {dr} {cut}\n{}{}{}", block(&f), block(&z), block(&rho));
    let grid = format!("{nrho} {drho} {nr} {dr} {cut}\n");
    let el = |name: &str, dens: usize| {
        let mut s = format!("29 63.55 3.615 FCC {name}\n{}", block(&f));
        for _ in 0..dens {
            s += &block(&rho);
        }
        s
    };
    let pairs = block(&rphi).repeat(3);
    let setfl = format!("c1\nc2\nc3\n2 Cu Cv\n{grid}{}{}{pairs}", el("Cu", 1), el("Cv", 1));
    let fs = format!("c1\nc2\nc3\n2 Cu Cv\n{grid}{}{}{pairs}", el("Cu", 2), el("Cv", 2));
    vec![("small.eam".into(), funcfl), ("small.eam.alloy".into(), setfl), ("small.eam.fs".into(), fs)]
}

#[test]
fn the_small_potentials_of_the_three_formats_are_valid() {
    for (name, text) in small_potentials() {
        let pot = Potential::from_text(&name, &text).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert!(pot.cutoff() == 5.0, "{name}");
    }
}

#[test]
fn fuzz_eam_potentials_of_the_three_formats() {
    let mut seeds = small_potentials();
    let u3 = std::fs::read_to_string(crate_dir().join("potentials/Cu_u3.eam")).unwrap();
    seeds.push(("Cu_u3.eam".into(), u3));
    fuzz("eam", &seeds, 30_000, |name, text| {
        if let Ok(pot) = Potential::from_text(name, text) {
            exercise_potential(pot);
        }
    });
}

#[test]
fn fuzz_the_shipped_setfl_and_fs_files() {
    // The 30 000-line Mishin file is slow to parse: fewer, header-biased mutations of it, read
    // as setfl and (one element: the same layout) as Finnis-Sinclair.
    let text = std::fs::read_to_string(crate_dir().join("potentials/Cu_mishin1.eam.alloy")).unwrap();
    let seeds = vec![("Cu_mishin1.eam.alloy".to_string(), text.clone()), ("Cu_mishin1.eam.fs".to_string(), text)];
    fuzz("mishin", &seeds, 1_000, |name, text| {
        if let Ok(pot) = Potential::from_text(name, text) {
            exercise_potential(pot);
        }
    });
}

/// A small data file with Masses, image flags and Velocities.
const SMALL_DATA: &str = "small\n\n4 atoms\n2 atom types\n\n0 3.615 xlo xhi\n0 3.615 ylo yhi\n-1 2.615 zlo zhi\n\nMasses\n\n1 63.55\n2 63.55\n\n\
Atoms # atomic\n\n1 1 0 0 -1\n2 1 1.8075 1.8075 -1 0 0 0\n3 1 1.8075 0 0.8075 1 -1 0\n4 1 0 1.8075 0.8075\n\nVelocities\n\n1 1 0 0\n2 0 1 0\n3 0 0 1\n4 -1 -1 -1\n";

#[test]
fn fuzz_lammps_data_files() {
    let pot = potential("Cu_u3.eam");
    let masses: Vec<f64> = (0..pot.n_elements()).map(|e| pot.mass(e)).collect();
    let hot = std::fs::read_to_string(crate_dir().join("tests/golden/cu108_hot.data")).unwrap();
    let seeds = vec![("small.data".to_string(), SMALL_DATA.to_string()), ("cu108_hot.data".to_string(), hot)];
    fuzz("data", &seeds, 60_000, |name, text| {
        let Ok(d) = DataFile::parse(text, name) else { return };
        // What parses writes back and reads again to the same atoms.
        let again = DataFile::parse(&d.to_text("again"), "again").unwrap_or_else(|e| panic!("written data does not read back: {e}"));
        assert_eq!((&again.ids, &again.x, &again.v), (&d.ids, &d.x, &d.v));
        // And goes into the engine as `md-worker eval` puts it (types beyond the potential's
        // elements are refused there).
        let s = d.box_spec(0);
        if let Ok(st) = md_worker::backend::prepare_box(&pot, &masses, &s) {
            assert!(st.meta.pe.is_finite(), "a box was built with a non-finite energy");
        }
    });
}

// Inputs that broke the engine, each found by reading the parsers with the fuzzers in mind.

#[test]
fn a_potential_header_asking_for_1e11_values_is_an_end_of_file_error_not_an_abort() {
    // Vec::with_capacity(1e11) aborted the process (allocation failure is not a panic).
    let (_, text) = small_potentials().remove(0);
    let text = text.replacen("60 0.05 200", "100000000000 0.05 200", 1);
    let e = Potential::from_text("big.eam", &text).unwrap_err().to_string();
    assert!(e.contains("unexpected end of file") && e.contains("100000000000 values of F(rho)"), "{e}");
}

#[test]
fn a_data_file_with_4294967295_atom_types_is_refused_without_allocating_them() {
    // The Masses table was allocated for every section: 32 GB for this header.
    let text = SMALL_DATA.replacen("2 atom types", "4294967295 atom types", 1);
    let e = DataFile::parse(&text, "types.data").unwrap_err().to_string();
    assert!(e.contains("types.data:") && e.contains("section Masses expects 4294967295 lines"), "{e}");
}

#[test]
fn a_potential_with_an_infinite_cutoff_is_refused_not_a_hang() {
    // cut = inf parsed (inf > 0): a neighbour reach of 2^31 cells would never end.
    let (_, text) = small_potentials().remove(0);
    let text = text.replacen("0.03 5\n", "0.03 inf\n", 1);
    let e = Potential::from_text("inf.eam", &text).unwrap_err().to_string();
    assert!(e.contains("inf.eam:3") && e.contains("cutoff = inf is not a finite number"), "{e}");
    // A large finite one: the box is refused against the neighbour radius.
    let text = text.replacen("0.03 inf\n", "0.03 1000\n", 1);
    let mut b = ReferenceBackend::new(Arc::new(Potential::from_text("huge.eam", &text).unwrap()));
    let e = b.open(&[BoxSpec::lattice(1, LatticeKind::Fcc, 3.615, [1, 1, 1])]).unwrap_err().to_string();
    assert!(e.contains("point 1") && e.contains("neighbour radius"), "{e}");
}

#[test]
fn written_data_of_a_file_with_an_atom_type_without_atoms_reads_back() {
    // Found by fuzz_lammps_data_files: `to_text` counted types by the atoms' largest type but
    // wrote every mass, so a type without atoms made a Masses row read as a section header.
    let d = DataFile::parse(SMALL_DATA, "small.data").unwrap();
    assert_eq!(d.masses.as_ref().map(Vec::len), Some(2));
    assert!(d.types.iter().all(|&t| t == 1));
    let again = DataFile::parse(&d.to_text("again"), "again").unwrap();
    assert_eq!((again.ids, again.types, again.x, again.v, again.masses), (d.ids, d.types, d.x, d.v, d.masses));
}

#[test]
fn a_funcfl_grid_spacing_of_1e308_is_refused_not_an_overflow() {
    // Found by fuzz_eam_potentials_of_the_three_formats (iteration 43832): dr = 1e308 made
    // rmax = (Nr - 1) dr infinite and the resampled table length usize::MAX ("attempt to add
    // with overflow" in resample).
    let (_, text) = small_potentials().remove(0);
    let text = text.replacen("60 0.05 200 0.03 5", "60 0.05 200 1e308 5", 1);
    let e = Potential::from_text("dr.eam", &text).unwrap_err().to_string();
    assert!(e.contains("dr.eam:3") && e.contains("not finite"), "{e}");
}

#[test]
fn a_cutoff_of_2e30_table_rows_is_refused_before_the_unchecked_conversion() {
    // The force kernel turns r / dr into an i32 without a check (r below the cut-off): a file
    // with cutoff / dr beyond 2^31 would have made that undefined behaviour.
    let (_, text) = small_potentials().remove(0);
    let text = text.replacen("0.03 5\n", "0.03 1e10\n", 1);
    let e = Potential::from_text("cut.eam", &text).unwrap_err().to_string();
    assert!(e.contains("cut.eam:3") && e.contains("at most 2^30"), "{e}");
}
