//! Run outputs: particle CSV snapshots, VTK files, PNG profiles, the state digest. Every file is
//! written atomically (temporary file in the same directory, fsync, rename), so an interrupted
//! run never leaves a half-written file under a final name.

use anyhow::{Context, Result};
use continuum::{Particles, tensor};
use sha2::{Digest, Sha256};
use std::fmt::Write as _;
use std::path::Path;

/// Writes `bytes` to `path` atomically ([`crate::atomic::write`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    crate::atomic::write(path, bytes)
}

/// Adds a LAMMPS text dump frame (`md_worker::data::dump_frame`) whose `ITEM: TIMESTEP` is `step`
/// to the dump file at `path`, atomically (the whole file is rewritten through
/// [`write_atomic`]). Frames already there with a timestep at or after `step` are dropped first,
/// so a run resumed from a checkpoint does not repeat the frames it writes again.
pub fn append_dump_frame(path: &Path, step: u64, frame: &str) -> Result<()> {
    const HEAD: &str = "ITEM: TIMESTEP\n";
    let old = match std::fs::read_to_string(path) {
        Ok(s) => s,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => String::new(),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
    };
    // Byte offset where the first frame at or after `step` starts (frames are in step order).
    let mut keep = old.len();
    let mut at = 0;
    while let Some(k) = old[at..].find(HEAD) {
        let start = at + k;
        let number = old[start + HEAD.len()..].lines().next().unwrap_or("");
        if number.trim().parse::<u64>().map_or(true, |t| t >= step) {
            keep = start;
            break;
        }
        at = start + HEAD.len();
    }
    let mut text = String::with_capacity(keep + frame.len());
    text.push_str(&old[..keep]);
    text.push_str(frame);
    write_atomic(path, text.as_bytes())
}

/// A number for a text file: non-finite values never reach a file (they become empty cells).
fn num(out: &mut String, v: f64) {
    if v.is_finite() {
        let _ = write!(out, "{v:e}");
    }
}

const AXES: [&str; 3] = ["x", "y", "z"];

/// Particle table: `id,x0,(y0,z0),x,(y,z),vx,(vy,vz),mass,volume,density,pressure,sxx..syz`,
/// then the `extra` columns (one value per point; non-finite values are written empty).
pub fn particles_csv<const D: usize>(pts: &Particles<D>, extra: &[(&str, Vec<f64>)]) -> String {
    let mut s = String::with_capacity(pts.len() * 200);
    s.push_str("id");
    for a in AXES.iter().take(D) {
        let _ = write!(s, ",{a}0");
    }
    for a in AXES.iter().take(D) {
        let _ = write!(s, ",{a}");
    }
    for a in AXES.iter().take(D) {
        let _ = write!(s, ",v{a}");
    }
    s.push_str(",mass,volume,density,pressure,sxx,syy,szz,sxy,sxz,syz");
    for (name, _) in extra {
        let _ = write!(s, ",{name}");
    }
    s.push('\n');
    for p in 0..pts.len() {
        let _ = write!(s, "{p}");
        for v in pts.x0[p].iter().chain(&pts.x[p]).chain(&pts.v[p]) {
            s.push(',');
            num(&mut s, *v);
        }
        for v in [pts.mass[p], pts.volume[p], pts.density(p), pts.pressure(p)].into_iter().chain(tensor::to_voigt(&pts.stress[p])) {
            s.push(',');
            num(&mut s, v);
        }
        for (_, col) in extra {
            s.push(',');
            num(&mut s, col.get(p).copied().unwrap_or(f64::NAN));
        }
        s.push('\n');
    }
    s
}

/// ASCII VTK unstructured grid of the points as vertices, with velocity, density, pressure,
/// mass, the concentration and equivalent plastic strain where the points carry them, the
/// body index, and the stress (SI).
pub fn particles_vtu<const D: usize>(pts: &Particles<D>) -> String {
    let n = pts.len();
    let mut s = String::with_capacity(n * 300);
    let _ = writeln!(
        s,
        "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\">\n<UnstructuredGrid>\n<Piece NumberOfPoints=\"{n}\" NumberOfCells=\"{n}\">"
    );
    let vec3 = |s: &mut String, v: &[f64]| {
        for a in 0..3 {
            num(s, v.get(a).copied().unwrap_or(0.0));
            s.push(' ');
        }
        s.push('\n');
    };
    s.push_str("<Points>\n<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n");
    for p in 0..n {
        vec3(&mut s, &pts.x[p]);
    }
    s.push_str("</DataArray>\n</Points>\n<Cells>\n<DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">\n");
    for p in 0..n {
        let _ = write!(s, "{p} ");
    }
    s.push_str("\n</DataArray>\n<DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">\n");
    for p in 0..n {
        let _ = write!(s, "{} ", p + 1);
    }
    s.push_str("\n</DataArray>\n<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n");
    for _ in 0..n {
        s.push_str("1 ");
    }
    s.push_str("\n</DataArray>\n</Cells>\n<PointData Scalars=\"pressure\" Vectors=\"velocity\">\n");
    s.push_str("<DataArray type=\"Float64\" Name=\"velocity\" NumberOfComponents=\"3\" format=\"ascii\">\n");
    for p in 0..n {
        vec3(&mut s, &pts.v[p]);
    }
    s.push_str("</DataArray>\n");
    for (name, f) in
        [("density", &(|p| pts.density(p)) as &dyn Fn(usize) -> f64), ("pressure", &|p| pts.pressure(p)), ("mass", &|p| pts.mass[p])]
    {
        let _ = writeln!(s, "<DataArray type=\"Float64\" Name=\"{name}\" format=\"ascii\">");
        for p in 0..n {
            num(&mut s, f(p));
            s.push(' ');
        }
        s.push_str("\n</DataArray>\n");
    }
    // The optional fields (concentration, equivalent plastic strain) and the body index.
    let body: Vec<f64> = pts.body.iter().map(|&b| b as f64).collect();
    for (name, values) in field_columns(pts).iter().map(|(n, v)| (*n, v.as_slice())).chain([("body", body.as_slice())]) {
        let _ = writeln!(s, "<DataArray type=\"Float64\" Name=\"{name}\" format=\"ascii\">");
        for v in values {
            num(&mut s, *v);
            s.push(' ');
        }
        s.push_str("\n</DataArray>\n");
    }
    s.push_str("<DataArray type=\"Float64\" Name=\"stress\" NumberOfComponents=\"9\" format=\"ascii\">\n");
    for p in 0..n {
        for v in pts.stress[p].iter().flatten() {
            num(&mut s, *v);
            s.push(' ');
        }
        s.push('\n');
    }
    s.push_str("</DataArray>\n</PointData>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>\n");
    s
}

/// The optional per-point fields as particle-file columns: `concentration` and
/// `plastic_strain` when the points carry them.
pub fn field_columns<const D: usize>(pts: &Particles<D>) -> Vec<(&'static str, Vec<f64>)> {
    let mut cols = Vec::new();
    if !pts.scalar.is_empty() {
        cols.push(("concentration", pts.scalar.clone()));
    }
    if !pts.plastic_strain.is_empty() {
        cols.push(("plastic_strain", pts.plastic_strain.clone()));
    }
    cols
}

/// ParaView collection of the snapshots: `(time, relative file)`.
pub fn pvd(entries: &[(f64, String)]) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n<Collection>\n");
    for (t, f) in entries {
        let _ = writeln!(s, "<DataSet timestep=\"{t:e}\" part=\"0\" file=\"{f}\"/>");
    }
    s.push_str("</Collection>\n</VTKFile>\n");
    s
}

/// SHA-256 over the bits of the final state (positions, velocities, volumes, deformation
/// gradients, stresses, energies, and the concentration and plastic strain of scenes that
/// carry them), the step and the time.
pub fn state_digest<const D: usize>(pts: &Particles<D>, step: u64, time: f64) -> String {
    let mut h = Sha256::new();
    h.update(step.to_le_bytes());
    h.update(time.to_bits().to_le_bytes());
    for p in 0..pts.len() {
        let scalars = pts.x[p].iter().chain(&pts.v[p]).chain([&pts.volume[p], &pts.internal_energy[p], &pts.visc_pressure[p]]);
        for v in scalars.chain(pts.def_grad[p].iter().flatten()).chain(pts.stress[p].iter().flatten()) {
            h.update(v.to_bits().to_le_bytes());
        }
    }
    // The optional fields, only when the scene has them (so every other digest is unchanged).
    for v in pts.scalar.iter().chain(&pts.plastic_strain) {
        h.update(v.to_bits().to_le_bytes());
    }
    hex::encode(h.finalize())
}

pub fn sha256_file(path: &Path) -> Result<String> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    Ok(hex::encode(Sha256::digest(&bytes)))
}

static FONT: &[u8] = include_bytes!("../assets/DejaVuSans.ttf");

/// A line profile: series of (x, y) points, drawn as dots (particles) or a line (exact).
pub struct Series<'a> {
    pub label: &'a str,
    pub points: Vec<(f64, f64)>,
    pub line: bool,
}

/// Writes a PNG plot of series against x.
pub fn plot_profile(path: &Path, title: &str, xlabel: &str, ylabel: &str, series: &[Series<'_>]) -> Result<()> {
    use plotters::prelude::*;
    use std::sync::Once;
    static REGISTER: Once = Once::new();
    REGISTER.call_once(|| {
        let _ = plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, FONT);
    });
    let finite = series.iter().flat_map(|s| s.points.iter()).filter(|(x, y)| x.is_finite() && y.is_finite());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in finite {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if !(x0 < x1) {
        return Ok(());
    }
    let pad = if y1 > y0 { 0.05 * (y1 - y0) } else { 0.5 * y0.abs().max(1e-12) };
    let (w, hgt) = (1000u32, 600u32);
    let mut buf = vec![0u8; (w * hgt * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, hgt)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 22))
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(90)
            .build_cartesian_2d(x0..x1, (y0 - pad)..(y1 + pad))
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        chart.configure_mesh().x_desc(xlabel).y_desc(ylabel).draw().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        // Ten distinguishable colours: a report over every scheme has up to ten series.
        let colors = [
            BLUE,
            RED,
            GREEN,
            BLACK,
            MAGENTA,
            CYAN,
            RGBColor(230, 120, 0),
            RGBColor(120, 60, 160),
            RGBColor(140, 80, 20),
            RGBColor(120, 120, 120),
        ];
        for (k, s) in series.iter().enumerate() {
            let color = colors[k % colors.len()];
            let pts: Vec<(f64, f64)> = s.points.iter().copied().filter(|(x, y)| x.is_finite() && y.is_finite()).collect();
            if s.line {
                // Lines join the points, and each point is marked, so a series of one run (or
                // two series on top of each other) still shows.
                chart.draw_series(pts.iter().map(|&p| Circle::new(p, 3, color.filled()))).map_err(|e| anyhow::anyhow!("plot: {e}"))?;
                chart
                    .draw_series(LineSeries::new(pts, color.stroke_width(2)))
                    .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                    .label(s.label)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color));
            } else {
                chart
                    .draw_series(pts.into_iter().map(|p| Circle::new(p, 1, color.filled())))
                    .map_err(|e| anyhow::anyhow!("plot: {e}"))?
                    .label(s.label)
                    .legend(move |(x, y)| Circle::new((x + 10, y), 3, color.filled()));
            }
        }
        chart
            .configure_series_labels()
            .border_style(BLACK)
            .background_style(WHITE.mix(0.8))
            .draw()
            .map_err(|e| anyhow::anyhow!("plot: {e}"))?;
        root.present().map_err(|e| anyhow::anyhow!("plot: {e}"))?;
    }
    write_atomic(path, &encode_png(&buf, w, hgt)?)
}

/// Encodes an RGB buffer as PNG.
fn encode_png(rgb: &[u8], w: u32, h: u32) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().context("cannot encode PNG")?;
        writer.write_image_data(rgb).context("cannot encode PNG")?;
    }
    Ok(out)
}

/// Log-log plot: the data are drawn as log10 values on linear axes (labelled so).
pub fn plot_loglog(path: &Path, title: &str, xlabel: &str, ylabel: &str, series: &[Series<'_>]) -> Result<()> {
    let logged: Vec<Series<'_>> = series
        .iter()
        .map(|s| Series {
            label: s.label,
            points: s.points.iter().filter(|(x, y)| *x > 0.0 && *y > 0.0).map(|(x, y)| (x.log10(), y.log10())).collect(),
            line: s.line,
        })
        .collect();
    plot_profile(path, title, &format!("log10 {xlabel}"), &format!("log10 {ylabel}"), &logged)
}

#[cfg(test)]
mod dump_tests {
    #![allow(clippy::unwrap_used)]
    use super::append_dump_frame;

    fn frame(step: u64) -> String {
        md_worker::data::dump_frame(step, [0.0; 3], [1.0; 3], &[1], &[1], &[[0.5; 3]], &[[0.0; 3]])
    }

    #[test]
    fn frames_append_in_order_and_a_resumed_run_replaces_the_later_ones() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("boxes/point-3.dump");
        for s in [0, 10, 20] {
            append_dump_frame(&path, s, &frame(s)).unwrap();
        }
        let all = frame(0) + &frame(10) + &frame(20);
        assert_eq!(std::fs::read_to_string(&path).unwrap(), all);
        // Resumed from a checkpoint at step 10: frames from step 10 on are written again.
        append_dump_frame(&path, 10, &frame(10)).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), frame(0) + &frame(10));
        append_dump_frame(&path, 20, &frame(20)).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), all);
        assert_eq!(std::fs::read_dir(dir.path().join("boxes")).unwrap().count(), 1, "no temporary file left");
    }
}
