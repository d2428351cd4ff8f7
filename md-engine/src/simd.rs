//! SIMD paths of the `cpu` back end's single-element EAM force kernel (AVX-512, AVX2), chosen
//! at run time ([`SimdPath::best`], or the `MSCALE_MD_SIMD` environment variable). Potentials
//! of several elements and LJ take the scalar kernel on every path.
//!
//! Bitwise the same as the scalar kernel (`kernel::eam_forces`), by construction: the
//! per-pair arithmetic (distance, square root, spline index and fraction, Horner values and
//! derivatives, division, force and virial products) is done 8 (AVX-512) or 4 (AVX2) pairs at
//! a time with exactly the scalar's operations in the scalar's order (IEEE `sqrt` and `div`,
//! separate multiplies and adds: no FMA contraction), and every sum (densities, forces,
//! energy, virial) is accumulated serially in the scalar's pair order. So every path gives
//! the same bits as the `reference` oracle, and a digest blessed on one path holds on all.
//!
//! Layout: the neighbour list stays CSR (`NeighborList`); the geometry pass loads neighbour
//! positions from a copy padded to 4 f64 per atom (8 row loads and a transpose rather than
//! gathers, which are slow on Zen 4), decodes image codes into shifts `n * L` arithmetically
//! (the same product as the scalar's shift table), tests the cut-off and compacts the pairs
//! inside it (AVX-512 `vcompress` in registers; AVX2 by mask bits) into structure-of-arrays
//! buffers (dx, dy, dz, r, i, j). Rows are processed in blocks of about [`BLOCK`] pairs: the
//! vector pass writes a block's per-pair terms into a small buffer that stays in L1, then a
//! serial pass accumulates them. Spline coefficients are read as whole rows (7 f64, LAMMPS
//! layout) and transposed in registers; element gathers measured 1.4x slower for the whole
//! kernel, and recomputing coefficients from a compact table would change the bits. A list
//! whose image table is not `neighbor::build`'s enumeration falls back to gathers.

use crate::error::MdError;
use crate::neighbor::NeighborList;
use crate::potential::EamTables;
use std::sync::OnceLock;

/// The environment variable that forces a path: `auto` (default), `scalar`, `avx2`, `avx512`.
pub const ENV: &str = "MSCALE_MD_SIMD";

/// A code path of the cpu back end's EAM kernel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum SimdPath {
    /// The scalar kernel (also the `reference` back end's, always).
    #[default]
    Scalar,
    /// 4 f64 lanes (AVX2; FMA is deliberately not used, see the module doc).
    Avx2,
    /// 8 f64 lanes (AVX-512 F, VL, BW).
    Avx512,
}

impl SimdPath {
    /// Every path, whether this CPU has it or not.
    pub const ALL: [SimdPath; 3] = [SimdPath::Scalar, SimdPath::Avx2, SimdPath::Avx512];

    /// `scalar`, `avx2` or `avx512`.
    pub fn name(self) -> &'static str {
        match self {
            SimdPath::Scalar => "scalar",
            SimdPath::Avx2 => "avx2",
            SimdPath::Avx512 => "avx512",
        }
    }

    /// Whether this CPU runs the path (run-time feature detection).
    pub fn is_supported(self) -> bool {
        match self {
            SimdPath::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            SimdPath::Avx2 => std::arch::is_x86_feature_detected!("avx2"),
            #[cfg(target_arch = "x86_64")]
            SimdPath::Avx512 => {
                std::arch::is_x86_feature_detected!("avx512f")
                    && std::arch::is_x86_feature_detected!("avx512vl")
                    && std::arch::is_x86_feature_detected!("avx512bw")
                    && std::arch::is_x86_feature_detected!("avx2")
            }
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The paths this CPU runs.
    pub fn supported() -> Vec<SimdPath> {
        Self::ALL.into_iter().filter(|p| p.is_supported()).collect()
    }

    /// The path `auto` takes: AVX-512 where the CPU has it, else scalar. The AVX2 path (4
    /// lanes, compaction by mask bits) measured no faster than scalar on AMD Zen 4
    /// (md-worker/docs/simd-measurements.md), so it runs only when asked for.
    pub fn best() -> SimdPath {
        if SimdPath::Avx512.is_supported() { SimdPath::Avx512 } else { SimdPath::Scalar }
    }

    /// A path from a value of [`ENV`]: `auto` (or empty) is [`SimdPath::best`]; a named path
    /// must be one this CPU runs.
    pub fn parse(value: &str) -> Result<SimdPath, MdError> {
        let v = value.trim().to_ascii_lowercase();
        let path = match v.as_str() {
            "" | "auto" => return Ok(SimdPath::best()),
            "scalar" => SimdPath::Scalar,
            "avx2" => SimdPath::Avx2,
            "avx512" => SimdPath::Avx512,
            _ => return Err(MdError::invalid(ENV, format!("{value:?}; expected auto, scalar, avx2 or avx512"))),
        };
        if !path.is_supported() {
            let have: Vec<&str> = Self::supported().into_iter().map(SimdPath::name).collect();
            return Err(MdError::invalid(
                ENV,
                format!("{value:?}: this CPU does not support {}; it supports {} (or unset the variable)", path.name(), have.join(", ")),
            ));
        }
        Ok(path)
    }
}

impl std::fmt::Display for SimdPath {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The path of the `cpu` back end (and `md-worker direct`) in this process: [`ENV`] if set,
/// else [`SimdPath::best`].
/// Read once per process.
pub fn selected() -> Result<SimdPath, MdError> {
    static SEL: OnceLock<Result<SimdPath, String>> = OnceLock::new();
    let r = SEL.get_or_init(|| match std::env::var(ENV) {
        Ok(v) => SimdPath::parse(&v).map_err(|e| e.to_string()),
        Err(std::env::VarError::NotPresent) => Ok(SimdPath::best()),
        Err(std::env::VarError::NotUnicode(v)) => Err(format!("invalid {ENV}: {v:?} is not unicode")),
    });
    r.clone().map_err(|msg| MdError::Invalid { what: ENV.into(), msg: msg.trim_start_matches(&format!("invalid {ENV}: ")).into() })
}

/// The name of [`selected`] for provenance, or `invalid` when the variable is bad.
pub fn selected_name() -> &'static str {
    selected().map_or("invalid", SimdPath::name)
}

/// Pairs per block of the vector and serial passes (the block's terms stay in L1).
pub const BLOCK: usize = 256;
/// Padding of the pair buffers beyond the list length (full-width stores and loads at the end).
const PAD: usize = 16;
/// Per-pair force terms in a block: fd x y z, phi, virial xx yy zz xy xz yz.
const TERMS: usize = 10;

/// Per-thread scratch of the SIMD kernel.
#[derive(Default)]
pub(crate) struct Scratch {
    dx: Vec<f64>,
    dy: Vec<f64>,
    dz: Vec<f64>,
    /// r^2 after the geometry pass, r after the density pass.
    r: Vec<f64>,
    i: Vec<i32>,
    j: Vec<i32>,
    /// List entry of each pair (only filled for the threaded kernel, `intra.rs`).
    k: Vec<i32>,
    /// Spline row offset (7 m) and fraction of each pair, written by the AVX-512 density
    /// pass and read by its force pass (offsets read from memory, not extracted from lanes).
    m7: Vec<i32>,
    frac: Vec<f64>,
    /// End of row i's pairs.
    row_end: Vec<u32>,
    /// A block's per-pair results.
    blk: Vec<f64>,
    /// Unwrapped positions padded to 4 f64 per atom (row loads instead of gathers).
    x4: Vec<f64>,
    /// The box kernel's filtered list ([`Inner`]).
    inner: Inner,
}

/// Extra radius (A) beyond the cut-off of the box kernel's filtered list ([`Inner`]). The
/// Mishin Cu fcc shell at 5.716 A lies 0.21 A beyond the 5.507 A cut-off, the next at 6.26 A;
/// measured (md-engine/README.md, h15y log) against 0.1 and 0.3.
pub const INNER_SKIN: f64 = 0.1;

/// A filtered copy of a neighbour list for [`eam_forces_one`]: the entries of each row that
/// were within `cut-off + INNER_SKIN` when it was filtered, in the list's order, and the
/// unwrapped positions and box then. While no atom has moved more than half the margin from
/// its affinely mapped filter-time position (the list builder's own criterion,
/// `kernel::needs_rebuild`, with the inner radius), every pair of the list within the
/// cut-off is in it, so the geometry pass reads only these entries and finds exactly the same
/// pairs in the same order: the results are bitwise those of the whole list, and which steps
/// re-filter (a function of the positions alone) changes nothing but the time. Kept per
/// thread, keyed by the list's `generation` (unique per build in the process).
#[derive(Default)]
struct Inner {
    /// `NeighborList::generation` it was filtered from (0: none), the cut-off^2 and skin bits.
    key: (u64, u64, u64),
    start: Vec<u32>,
    j: Vec<u32>,
    code: Vec<u16>,
    xref: Vec<[f64; 3]>,
    lo: [f64; 3],
    l: [f64; 3],
    /// Filters and evaluations in this thread (tests read them: the list must be reused).
    filters: u64,
    evaluations: u64,
}

impl Inner {
    /// Whether the filtered list still holds every pair within `rc` of the list built with
    /// key `key` for its `rows` rows, whose pairs name the atoms `atoms` (None: every atom of
    /// `xu`), for unwrapped positions `xu` in the box (`lo`, `l`).
    #[allow(clippy::too_many_arguments)]
    fn valid(&self, key: (u64, u64, u64), xu: &[[f64; 3]], atoms: Option<&[u32]>, rows: usize, lo: [f64; 3], l: [f64; 3], rc: f64) -> bool {
        let m = atoms.map_or(xu.len(), <[u32]>::len);
        if key.0 == 0 || self.key != key || self.xref.len() != m || self.start.len() != rows + 1 {
            return false;
        }
        let ratio: [f64; 3] = std::array::from_fn(|d| l[d] / self.l[d]);
        let min_ratio = ratio[0].min(ratio[1]).min(ratio[2]);
        // As `kernel::needs_rebuild`, with a relative 1e-12 kept for round-off: an entry left
        // out was at least rc + INNER_SKIN away (as computed) when filtered.
        let margin = min_ratio * (rc + INNER_SKIN) * (1.0 - 1e-12) - rc * (1.0 + 1e-12);
        if !(margin > 0.0) {
            return false;
        }
        let lim = 0.25 * margin * margin;
        self.xref.iter().enumerate().all(|(w, q)| {
            let p = xu[atoms.map_or(w, |a| a[w] as usize)];
            let mut d2 = 0.0;
            for d in 0..3 {
                let e = p[d] - (lo[d] + (q[d] - self.lo[d]) * ratio[d]);
                d2 += e * e;
            }
            d2 <= lim
        })
    }

    /// How this evaluation reads its rows (see [`valid`](Self::valid) for the arguments):
    /// the filtered list while valid, else the whole list, re-filtered on the way (prepared
    /// here) when `filtering` (decodable images and a skin wider than the filter's).
    #[allow(clippy::too_many_arguments)]
    fn begin(
        &mut self,
        filtering: bool,
        key: (u64, u64, u64),
        xu: &[[f64; 3]],
        atoms: Option<&[u32]>,
        rows: usize,
        lo: [f64; 3],
        l: [f64; 3],
        rc: f64,
        cap: usize,
    ) -> Filtering {
        self.evaluations += 1;
        if !filtering {
            return Filtering::Off;
        }
        if self.valid(key, xu, atoms, rows, lo, l, rc) {
            return Filtering::Reuse;
        }
        self.filters += 1;
        self.key = key;
        self.start.clear();
        self.start.push(0);
        self.j.clear();
        self.code.clear();
        self.xref.clear();
        match atoms {
            Some(a) => self.xref.extend(a.iter().map(|&w| xu[w as usize])),
            None => self.xref.extend_from_slice(xu),
        }
        (self.lo, self.l) = (lo, l);
        // The filtering geometry pass stores 8 entries at a time from the filtered length.
        self.j.reserve(cap);
        self.code.reserve(cap);
        Filtering::Refilter
    }

    /// After the last row: the padding that `geometry4::<_, true>` reads unmasked (atom 0).
    fn end(&mut self, mode: Filtering) {
        if mode == Filtering::Refilter {
            self.j.extend([0; 8]);
            self.code.extend([0; 8]);
        }
    }
}

/// How an evaluation reads the rows of its neighbour list ([`Inner::begin`]).
#[derive(Clone, Copy, PartialEq, Eq)]
enum Filtering {
    /// The whole list.
    Off,
    /// The filtered list.
    Reuse,
    /// The whole list, filtered into [`Inner`] on the way.
    Refilter,
}

/// What the geometry of a row reads (the box and the block kernels).
struct RowInput<'a> {
    path: SimdPath,
    list: &'a NeighborList,
    xu: &'a [[f64; 3]],
    shift: &'a [[f64; 3]],
    /// Positions padded to 4 f64 per atom (used with `images`).
    x4: *const f64,
    images: Option<&'a Images>,
    cut2: f64,
    /// (cut-off + [`INNER_SKIN`])^2, the filter's radius squared.
    rin2: f64,
}

/// Row `i` (row `r` of the evaluation's rows, `Inner`'s numbering) read as `mode` says: its
/// pairs within the cut-off appended to `s` from `np` in list order (and, when re-filtering,
/// its entries within the filter's radius appended to `inner`); returns the new `np`.
///
/// # Safety
/// `g.path` is supported by the CPU; `s`'s pair buffers hold `np` + the row's length + 8
/// entries (`s.k` too when re-filtering off AVX-512); `inner.j`/`code` have room for the
/// row's length + 8 more when re-filtering; without `images`, every atom and code of the list
/// indexes `xu`/`shift` (the vector paths check them as they load otherwise).
unsafe fn geometry_row(g: &RowInput, mode: Filtering, inner: &mut Inner, s: &mut Scratch, i: usize, r: usize, np: usize) -> usize {
    let list = g.list;
    let n = g.xu.len();
    let row = list.start[i] as usize..list.start[i + 1] as usize;
    let (js, codes) = if mode == Filtering::Reuse {
        let f = inner.start[r] as usize..inner.start[r + 1] as usize;
        (&inner.j[f.clone()], &inner.code[f])
    } else {
        (&list.j[row.clone()], &list.code[row.clone()])
    };
    let rin2 = g.rin2;
    let (xp, sp) = (g.xu.as_ptr() as *const f64, g.shift.as_ptr() as *const f64);
    let xi = g.xu[i];
    // SAFETY: the caller's contract; the padded reads of `geometry4::<_, true>` stay inside
    // the filtered list's padding ([`Inner::end`]).
    let np1 = unsafe {
        match (g.path, mode, g.images) {
            #[cfg(target_arch = "x86_64")]
            (SimdPath::Avx512, Filtering::Reuse, Some(img)) => {
                avx512::geometry4::<false, true>(xi, js, codes, g.x4, img, n, g.cut2, s, i, np, 0)
            }
            #[cfg(target_arch = "x86_64")]
            (SimdPath::Avx512, Filtering::Off, Some(img)) => {
                avx512::geometry4::<false, false>(xi, js, codes, g.x4, img, n, g.cut2, s, i, np, 0)
            }
            #[cfg(target_arch = "x86_64")]
            (SimdPath::Avx512, Filtering::Refilter, Some(img)) => {
                let no = inner.j.len();
                let (np1, no1) = avx512::geometry4_filter(
                    xi,
                    &list.j[row.clone()],
                    &list.code[row.clone()],
                    g.x4,
                    img,
                    n,
                    g.cut2,
                    rin2,
                    s,
                    i,
                    np,
                    inner.j.as_mut_ptr(),
                    inner.code.as_mut_ptr(),
                    no,
                );
                inner.j.set_len(no1);
                inner.code.set_len(no1);
                np1
            }
            #[cfg(target_arch = "x86_64")]
            (SimdPath::Avx512, _, None) => avx512::geometry(xi, js, codes, xp, sp, g.cut2, s, i, np),
            #[cfg(target_arch = "x86_64")]
            (SimdPath::Avx2, Filtering::Refilter, Some(img)) => {
                // Every entry within the filter's radius, with its list entry, then those
                // within the cut-off compacted in place.
                let np1 =
                    avx2::geometry4::<true>(xi, &list.j[row.clone()], &list.code[row.clone()], g.x4, img, n, rin2, s, i, np, row.start);
                let mut w = np;
                for q in np..np1 {
                    let k = s.k[q] as usize;
                    inner.j.push(list.j[k]);
                    inner.code.push(list.code[k]);
                    let keep = s.r[q] < g.cut2;
                    (s.dx[w], s.dy[w], s.dz[w], s.r[w], s.j[w]) = (s.dx[q], s.dy[q], s.dz[q], s.r[q], s.j[q]);
                    w += keep as usize;
                }
                w
            }
            #[cfg(target_arch = "x86_64")]
            (SimdPath::Avx2, _, Some(img)) => avx2::geometry4::<false>(xi, js, codes, g.x4, img, n, g.cut2, s, i, np, 0),
            #[cfg(target_arch = "x86_64")]
            (SimdPath::Avx2, _, None) => avx2::geometry(xi, js, codes, xp, sp, g.cut2, s, i, np),
            _ => {
                // The scalar kernel's geometry.
                let mut np = np;
                for (&j, &c) in js.iter().zip(codes) {
                    let (xj, sf) = (g.xu[j as usize], g.shift[c as usize]);
                    let d = [xi[0] - xj[0] - sf[0], xi[1] - xj[1] - sf[1], xi[2] - xj[2] - sf[2]];
                    let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
                    if r2 < g.cut2 {
                        (s.dx[np], s.dy[np], s.dz[np], s.r[np]) = (d[0], d[1], d[2], r2);
                        (s.i[np], s.j[np]) = (i as i32, j as i32);
                        np += 1;
                    }
                }
                np
            }
        }
    };
    if mode == Filtering::Refilter {
        inner.start.push(inner.j.len() as u32);
    }
    np1
}

/// (filters, evaluations) of [`eam_forces_one`]'s filtered list on this thread so far.
#[cfg(test)]
pub(crate) fn inner_counts() -> (u64, u64) {
    crate::kernel::with_simd_scratch(|s| (s.inner.filters, s.inner.evaluations))
}

/// How the list's image codes decode (`neighbor::build`'s enumeration), and the box lengths.
pub(crate) struct Images {
    ncodes: usize,
    /// span[1] * span[2] and span[2], as f64.
    s12: f64,
    s2: f64,
    /// Largest |image| per axis, as f64.
    h: [f64; 3],
    l: [f64; 3],
    /// For at most [`LUT`] codes (every box whose sides are at least the neighbour radius):
    /// each code's shift `n * L` per axis (`lut[d][code]`, the scalar's shift-table product),
    /// looked up by two-table permutes instead of decoded arithmetically (a long latency
    /// chain that was a third of the geometry pass).
    lut: Option<[[f64; LUT]; 3]>,
}

/// Codes the geometry pass looks up in registers (four 8-lane tables per axis).
const LUT: usize = 32;

impl Images {
    /// The decoding of `list.images` (None if they are not `neighbor::build`'s enumeration).
    fn of(list: &NeighborList, l: [f64; 3]) -> Option<Images> {
        let first = *list.images.first()?;
        let h = [-first[0], -first[1], -first[2]];
        let span = [2 * h[0] + 1, 2 * h[1] + 1, 2 * h[2] + 1];
        if span.iter().any(|&s| s < 1) || (span[0] * span[1] * span[2]) as usize != list.images.len() || list.images.len() > 1 << 16 {
            return None;
        }
        let lut = (list.images.len() <= LUT).then(|| {
            let mut t = [[0.0; LUT]; 3];
            for (c, n) in list.images.iter().enumerate() {
                for d in 0..3 {
                    t[d][c] = n[d] as f64 * l[d];
                }
            }
            t
        });
        let img = Images { ncodes: list.images.len(), s12: (span[1] * span[2]) as f64, s2: span[2] as f64, h: h.map(|x| x as f64), l, lut };
        // The enumeration a, b, c (c fastest) from -h to h.
        let ok = list.images.iter().enumerate().all(|(k, n)| {
            let k = k as i32;
            *n == [k / (span[1] * span[2]) - h[0], (k / span[2]) % span[1] - h[1], k % span[2] - h[2]]
        });
        ok.then_some(img)
    }
}

#[cold]
#[inline(never)]
fn bad_list(n: usize, ncodes: usize) -> ! {
    panic!("neighbour list names an atom >= {n} or an image code >= {ncodes}: not built for this box")
}

/// What the vector passes read of the tables.
struct Tab {
    dens: *const f64,
    z2: *const f64,
    rdr: f64,
    nr1: i32,
    cut2: f64,
}

/// EAM forces of a single-element potential on `path` (not `Scalar`): bitwise the same as
/// `kernel::eam_forces::<true>`. Returns (potential energy, virial); forces are added to `f`
/// (zeroed by the caller).
#[allow(clippy::too_many_arguments)]
pub(crate) fn eam_forces_one(
    path: SimdPath,
    t: &EamTables,
    types: &[u32],
    list: &NeighborList,
    xu: &[[f64; 3]],
    shift: &[[f64; 3]],
    lo: [f64; 3],
    l: [f64; 3],
    skin: f64,
    f: &mut [[f64; 3]],
    rho: &mut Vec<f64>,
    fp: &mut Vec<f64>,
    s: &mut Scratch,
) -> (f64, [f64; 6]) {
    // The intrinsics below are only sound on a CPU that has them.
    assert!(path != SimdPath::Scalar && path.is_supported(), "simd path {path} not runnable here");
    assert!(t.masses.len() == 1 && t.nr >= 2 && xu.len() == f.len() && xu.len() + 1 == list.start.len());
    let n = xu.len();
    let cap = list.len() + PAD;
    for v in [&mut s.dx, &mut s.dy, &mut s.dz, &mut s.r, &mut s.frac] {
        if v.len() < cap {
            v.resize(cap, 0.0);
        }
    }
    for v in [&mut s.i, &mut s.j, &mut s.m7] {
        if v.len() < cap {
            v.resize(cap, 0);
        }
    }
    let tab = Tab {
        dens: t.rhor[t.type2rhor[0][0]].as_ptr() as *const f64,
        z2: t.z2r[t.type2z2r[0][0]].as_ptr() as *const f64,
        rdr: t.rdr,
        nr1: (t.nr - 1) as i32,
        cut2: t.cutforcesq,
    };
    // Row loads read 8 f64 from any row m <= nr - 1 (rows 0..=nr exist).
    assert!(t.rhor[t.type2rhor[0][0]].len() > t.nr && t.z2r[t.type2z2r[0][0]].len() > t.nr);
    // The geometry passes decode image codes arithmetically and check atoms and codes as they
    // load; for a list whose images they cannot decode, the gathers need it checked here.
    let images = Images::of(list, l);
    if images.is_none() {
        assert!(list.j.iter().all(|&j| (j as usize) < n) && list.code.iter().all(|&c| (c as usize) < shift.len()));
    }
    s.x4.clear();
    if images.is_some() {
        s.x4.extend(xu.iter().flat_map(|p| [p[0], p[1], p[2], 0.0]));
    }
    let x4 = s.x4.as_ptr();
    rho.clear();
    rho.resize(n, 0.0);
    s.row_end.clear();
    s.row_end.reserve(n);
    // The filtered list: used while valid, else re-filtered in this evaluation's geometry pass
    // (only with decodable images and a skin wider than the filter's).
    let mut inner = std::mem::take(&mut s.inner);
    let key = (list.generation, t.cutforcesq.to_bits(), skin.to_bits());
    let mode = inner.begin(images.is_some() && INNER_SKIN < skin, key, xu, None, n, lo, l, t.cutoff, cap);
    if mode == Filtering::Refilter && s.k.len() < cap {
        s.k.resize(cap, 0);
    }
    let rin = t.cutoff + INNER_SKIN;
    let g = RowInput { path, list, xu, shift, x4, images: images.as_ref(), cut2: tab.cut2, rin2: rin * rin };
    // Density pass.
    let mut np = 0usize;
    let mut i0 = 0;
    while i0 < n {
        let q0 = np;
        let mut i1 = i0;
        while i1 < n && np - q0 < BLOCK {
            // SAFETY: the path is supported (asserted); atoms and codes are checked (above,
            // or as they load); every buffer holds list.len() + PAD entries and
            // np + the row's length <= list.len() (a filtered row is a part of its list row);
            // `inner` has room reserved by `begin`.
            np = unsafe { geometry_row(&g, mode, &mut inner, s, i1, i1, np) };
            s.row_end.push(np as u32);
            i1 += 1;
        }
        // Harmless lanes after the last pair (the vector passes read up to a full width).
        for q in np..np + 8 {
            (s.dx[q], s.dy[q], s.dz[q], s.r[q], s.i[q], s.j[q], s.m7[q], s.frac[q]) = (0.0, 0.0, 0.0, 1.0, 0, 0, 0, 0.0);
        }
        let len = np - q0;
        if s.blk.len() < len + 8 {
            s.blk.resize(len + 8, 0.0);
        }
        // SAFETY: as above; r[q0..np + 8) are valid distances, blk holds len + 8.
        unsafe {
            match path {
                #[cfg(target_arch = "x86_64")]
                SimdPath::Avx512 => avx512::density(&tab, s, q0, len),
                #[cfg(target_arch = "x86_64")]
                SimdPath::Avx2 => avx2::density(&tab, s, q0, len),
                _ => unreachable!("checked above"),
            }
        }
        let mut q = q0;
        for i in i0..i1 {
            let end = s.row_end[i] as usize;
            let mut rho_i = 0.0;
            while q < end {
                // SAFETY: q < np <= the buffers' length, q - q0 < len <= blk's, and every
                // j < n (checked by the geometry pass or the scan above).
                unsafe {
                    let v = *s.blk.get_unchecked(q - q0);
                    rho_i += v;
                    *rho.get_unchecked_mut(*s.j.get_unchecked(q) as usize) += v;
                }
                q += 1;
            }
            rho[i] += rho_i;
        }
        i0 = i1;
    }
    inner.end(mode);
    s.inner = inner;
    // Embedding pass (as the scalar kernel).
    let mut pe = 0.0;
    fp.clear();
    fp.resize(n, 0.0);
    for i in 0..n {
        let (phi, d) = t.embed(types[i] as usize, rho[i]);
        fp[i] = d;
        pe += phi;
    }
    // Force pass.
    let mut w = [0.0f64; 6];
    let (mut i0, mut q0) = (0usize, 0usize);
    while i0 < n {
        let mut i1 = i0 + 1;
        while i1 < n && s.row_end[i1] as usize - q0 <= BLOCK {
            i1 += 1;
        }
        let q1 = s.row_end[i1 - 1] as usize;
        let len = q1 - q0;
        let bl = len + 8;
        if s.blk.len() < TERMS * bl {
            s.blk.resize(TERMS * bl, 0.0);
        }
        // SAFETY: as above; pairs q0..q1 + 8 are valid (real or padding), blk holds TERMS * bl.
        unsafe {
            match path {
                #[cfg(target_arch = "x86_64")]
                SimdPath::Avx512 => avx512::force(&tab, s, fp.as_ptr(), q0, len, bl),
                #[cfg(target_arch = "x86_64")]
                SimdPath::Avx2 => avx2::force(&tab, s, fp.as_ptr(), q0, len, bl),
                _ => unreachable!("checked above"),
            }
        }
        let b = &s.blk;
        let mut q = q0;
        for i in i0..i1 {
            let end = s.row_end[i] as usize;
            let mut fi = [0.0; 3];
            while q < end {
                let k = q - q0;
                // SAFETY: k < len < bl and blk holds TERMS * bl; q < np; every j < n.
                unsafe {
                    let at = |t: usize| *b.get_unchecked(t * bl + k);
                    let fd = [at(0), at(1), at(2)];
                    pe += at(3);
                    fi[0] += fd[0];
                    fi[1] += fd[1];
                    fi[2] += fd[2];
                    let fj = f.get_unchecked_mut(*s.j.get_unchecked(q) as usize);
                    fj[0] -= fd[0];
                    fj[1] -= fd[1];
                    fj[2] -= fd[2];
                    for c in 0..6 {
                        w[c] += at(4 + c);
                    }
                }
                q += 1;
            }
            let fo = &mut f[i];
            fo[0] += fi[0];
            fo[1] += fi[1];
            fo[2] += fi[2];
        }
        i0 = i1;
        q0 = q1;
    }
    (pe, w)
}

/// What the blocks of the threaded kernel (`intra.rs`) share for one force evaluation.
pub(crate) struct Shared<'a> {
    path: SimdPath,
    tab: Tab,
    t: &'a EamTables,
    list: &'a NeighborList,
    xu: &'a [[f64; 3]],
    shift: &'a [[f64; 3]],
    /// Positions padded to 4 f64 per atom (empty when `images` is None).
    x4: Vec<f64>,
    images: Option<Images>,
    lo: [f64; 3],
    l: [f64; 3],
    skin: f64,
}

// SAFETY: `Tab`'s pointers address the potential's tables, borrowed for 'a and only read.
unsafe impl Sync for Shared<'_> {}

impl<'a> Shared<'a> {
    /// The shared state of one evaluation on `path` (any path, `Scalar` included), for the box
    /// (`lo`, `l`) and a list built with `skin`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn new(
        path: SimdPath,
        t: &'a EamTables,
        list: &'a NeighborList,
        xu: &'a [[f64; 3]],
        shift: &'a [[f64; 3]],
        lo: [f64; 3],
        l: [f64; 3],
        skin: f64,
    ) -> Shared<'a> {
        assert!(path.is_supported(), "simd path {path} not runnable here");
        assert!(t.masses.len() == 1 && t.nr >= 2 && xu.len() + 1 == list.start.len());
        assert!(t.rhor[t.type2rhor[0][0]].len() > t.nr && t.z2r[t.type2z2r[0][0]].len() > t.nr);
        let n = xu.len();
        let tab = Tab {
            dens: t.rhor[t.type2rhor[0][0]].as_ptr() as *const f64,
            z2: t.z2r[t.type2z2r[0][0]].as_ptr() as *const f64,
            rdr: t.rdr,
            nr1: (t.nr - 1) as i32,
            cut2: t.cutforcesq,
        };
        // The scalar geometry (and the vector paths without a decodable image table) index
        // xu and shift directly: check the list once here.
        let images = if path == SimdPath::Scalar { None } else { Images::of(list, l) };
        if images.is_none() {
            assert!(list.j.iter().all(|&j| (j as usize) < n) && list.code.iter().all(|&c| (c as usize) < shift.len()));
        }
        let x4 = if images.is_some() { xu.iter().flat_map(|p| [p[0], p[1], p[2], 0.0]).collect() } else { Vec::new() };
        Shared { path, tab, t, list, xu, shift, x4, images, lo, l, skin }
    }
}

/// Spline row and fraction of r, as `kernel::eam_forces`'s `index` (r below the cut-off).
#[inline(always)]
fn spline_index(r: f64, rdr: f64, nr: usize) -> (usize, f64) {
    let p = r * rdr + 1.0;
    // SAFETY: p is finite and 1 <= p < 2^31 (r below the cut-off, rdr = 1/dr).
    let m = (unsafe { p.to_int_unchecked::<i32>() } as usize).min(nr - 1);
    (m, (p - m as f64).min(1.0))
}

/// Threaded kernel, first pass of one block of rows: the pairs within the cut-off of rows
/// `rows` into `s` (kept for [`block_force`]; each pair's window slot in `s.k`), and the
/// block's density sums into its window `win` (zeroed here). The window's slots are the atoms
/// `atoms` (the rows first, in order, then every neighbour the rows' list entries name);
/// `map` is per-thread scratch of one entry per atom. Within the block the additions are the
/// serial kernels' (`rho[j] += v` in list order, each row's own sum added after its row), on
/// every path. The rows read the block's own filtered list (`s`'s [`Inner`], as the box kernel
/// does; bitwise the same pairs in the same order).
pub(crate) fn block_density(sh: &Shared, rows: std::ops::Range<usize>, s: &mut Scratch, atoms: &[u32], map: &mut [u32], win: &mut [f64]) {
    let list = sh.list;
    let n = sh.xu.len();
    let ne = list.start[rows.end] as usize - list.start[rows.start] as usize;
    assert!(win.len() == atoms.len() && atoms.len() >= rows.len() && map.len() == n);
    assert!(atoms[..rows.len()].iter().zip(rows.clone()).all(|(&a, i)| a as usize == i));
    let cap = ne + PAD;
    for v in [&mut s.dx, &mut s.dy, &mut s.dz, &mut s.r, &mut s.frac] {
        if v.len() < cap {
            v.resize(cap, 0.0);
        }
    }
    for v in [&mut s.i, &mut s.j, &mut s.k, &mut s.m7] {
        if v.len() < cap {
            v.resize(cap, 0);
        }
    }
    s.row_end.clear();
    let mut inner = std::mem::take(&mut s.inner);
    let key = (list.generation, sh.tab.cut2.to_bits(), sh.skin.to_bits());
    let filtering = sh.images.is_some() && INNER_SKIN < sh.skin;
    let mode = inner.begin(filtering, key, sh.xu, Some(atoms), rows.len(), sh.lo, sh.l, sh.t.cutoff, cap);
    let rin = sh.t.cutoff + INNER_SKIN;
    let g = RowInput {
        path: sh.path,
        list,
        xu: sh.xu,
        shift: sh.shift,
        x4: sh.x4.as_ptr(),
        images: sh.images.as_ref(),
        cut2: sh.tab.cut2,
        rin2: rin * rin,
    };
    let mut np = 0usize;
    for (r, i) in rows.clone().enumerate() {
        // SAFETY: the path is supported (asserted in `Shared::new`); atoms and codes are
        // checked there or as they load; the buffers hold ne + PAD entries and np + the row's
        // length <= ne; `inner` has room reserved by `begin`.
        np = unsafe { geometry_row(&g, mode, &mut inner, s, i, r, np) };
        s.row_end.push(np as u32);
    }
    inner.end(mode);
    s.inner = inner;
    // Each pair's window slot (every neighbour of the rows is in `atoms`).
    for (w, &a) in atoms.iter().enumerate() {
        map[a as usize] = w as u32;
    }
    for q in 0..np {
        s.k[q] = map[s.j[q] as usize] as i32;
    }
    // Harmless lanes after the last pair (the vector passes read up to a full width).
    for q in np..np + 8 {
        (s.dx[q], s.dy[q], s.dz[q], s.r[q], s.i[q], s.j[q], s.k[q], s.m7[q], s.frac[q]) = (0.0, 0.0, 0.0, 1.0, 0, 0, 0, 0, 0.0);
    }
    if s.blk.len() < np + 8 {
        s.blk.resize(np + 8, 0.0);
    }
    match sh.path {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: r[0..np + 8) are valid distances, blk holds np + 8; spline rows exist.
        SimdPath::Avx512 => unsafe { avx512::density(&sh.tab, s, 0, np) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        SimdPath::Avx2 => unsafe { avx2::density(&sh.tab, s, 0, np) },
        _ => {
            let dens = &sh.t.rhor[sh.t.type2rhor[0][0]];
            for q in 0..np {
                let r = s.r[q].sqrt();
                s.r[q] = r;
                let (m, p) = spline_index(r, sh.t.rdr, sh.t.nr);
                let c = &dens[m];
                s.blk[q] = ((c[3] * p + c[4]) * p + c[5]) * p + c[6];
            }
        }
    }
    win.fill(0.0);
    let mut q = 0;
    for (ri, &end) in s.row_end.iter().enumerate() {
        let mut rho_i = 0.0;
        while q < end as usize {
            let v = s.blk[q];
            rho_i += v;
            win[s.k[q] as usize] += v;
            q += 1;
        }
        win[ri] += rho_i;
    }
}

/// Threaded kernel, second pass of one block (after [`block_density`] on the same `s` and
/// `rows`, and the embedding pass of every atom: `fp`): the block's force sums into its window
/// `winf` (zeroed here; the slots [`block_density`] left in `s.k`: `f[j] -= d * fpair` in list order, each
/// row's own sum added after its row); returns the block's pair energy and virial, summed in
/// pair order.
pub(crate) fn block_force(
    sh: &Shared,
    rows: std::ops::Range<usize>,
    s: &mut Scratch,
    fp: &[f64],
    winf: &mut [[f64; 3]],
) -> (f64, [f64; 6]) {
    assert!(winf.len() >= rows.len() && s.row_end.len() == rows.len());
    assert!(fp.len() == sh.xu.len());
    let np = s.row_end.last().map_or(0, |e| *e as usize);
    winf.fill([0.0; 3]);
    let (mut pe, mut w) = (0.0, [0.0f64; 6]);
    let mut row = 0usize;
    let mut fi = [0.0f64; 3];
    let dens = &sh.t.rhor[sh.t.type2rhor[0][0]];
    let z2 = &sh.t.z2r[sh.t.type2z2r[0][0]];
    let mut q0 = 0;
    loop {
        let len = (np - q0).min(BLOCK);
        let bl = len + 8;
        if s.blk.len() < TERMS * bl {
            s.blk.resize(TERMS * bl, 0.0);
        }
        match sh.path {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: pairs q0..q0 + len + 8 are valid (real or padding), i and j index fp,
            // blk holds TERMS * bl.
            SimdPath::Avx512 => unsafe { avx512::force(&sh.tab, s, fp.as_ptr(), q0, len, bl) },
            #[cfg(target_arch = "x86_64")]
            // SAFETY: as above.
            SimdPath::Avx2 => unsafe { avx2::force(&sh.tab, s, fp.as_ptr(), q0, len, bl) },
            _ => {
                // `kernel::eam_forces::<true>`'s per-pair arithmetic.
                for k in 0..len {
                    let q = q0 + k;
                    let (d, r) = ([s.dx[q], s.dy[q], s.dz[q]], s.r[q]);
                    let (i, j) = (s.i[q] as usize, s.j[q] as usize);
                    let (m, p) = spline_index(r, sh.t.rdr, sh.t.nr);
                    let (cd, c) = (&dens[m], &z2[m]);
                    let rho_p = (cd[0] * p + cd[1]) * p + cd[2];
                    let z2p = (c[0] * p + c[1]) * p + c[2];
                    let z2v = ((c[3] * p + c[4]) * p + c[5]) * p + c[6];
                    let recip = 1.0 / r;
                    let phi = z2v * recip;
                    let phip = z2p * recip - phi * recip;
                    let psip = fp[i] * rho_p + fp[j] * rho_p + phip;
                    let fpair = -psip * recip;
                    let fd = [d[0] * fpair, d[1] * fpair, d[2] * fpair];
                    let t = [fd[0], fd[1], fd[2], phi, d[0] * fd[0], d[1] * fd[1], d[2] * fd[2], d[0] * fd[1], d[0] * fd[2], d[1] * fd[2]];
                    for (c, v) in t.into_iter().enumerate() {
                        s.blk[c * bl + k] = v;
                    }
                }
            }
        }
        for k in 0..len {
            let q = q0 + k;
            while q >= s.row_end[row] as usize {
                add3(&mut winf[row], fi);
                fi = [0.0; 3];
                row += 1;
            }
            let at = |t: usize| s.blk[t * bl + k];
            let fd = [at(0), at(1), at(2)];
            pe += at(3);
            fi[0] += fd[0];
            fi[1] += fd[1];
            fi[2] += fd[2];
            let fj = &mut winf[s.k[q] as usize];
            fj[0] -= fd[0];
            fj[1] -= fd[1];
            fj[2] -= fd[2];
            for c in 0..6 {
                w[c] += at(4 + c);
            }
        }
        q0 += len;
        if q0 >= np {
            break;
        }
    }
    while row < rows.len() {
        add3(&mut winf[row], fi);
        fi = [0.0; 3];
        row += 1;
    }
    (pe, w)
}

#[inline(always)]
fn add3(a: &mut [f64; 3], b: [f64; 3]) {
    a[0] += b[0];
    a[1] += b[1];
    a[2] += b[2];
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{Scratch, Tab};
    use std::arch::x86_64::*;

    #[inline]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    unsafe fn gather(idx: __m256i, base: *const f64) -> __m512d {
        // SAFETY: the caller's indices are inside the table at `base`.
        unsafe { _mm512_i32gather_pd::<8>(idx, base) }
    }

    /// Spline row (times 7, the row stride) and fraction, as `kernel::eam_forces`'s `index`.
    #[inline]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    fn index(r: __m512d, t: &Tab) -> (__m256i, __m512d) {
        let p = _mm512_add_pd(_mm512_mul_pd(r, _mm512_set1_pd(t.rdr)), _mm512_set1_pd(1.0));
        let m = _mm256_min_epi32(_mm512_cvttpd_epi32(p), _mm256_set1_epi32(t.nr1));
        let frac = _mm512_min_pd(_mm512_sub_pd(p, _mm512_cvtepi32_pd(m)), _mm512_set1_pd(1.0));
        (_mm256_mullo_epi32(m, _mm256_set1_epi32(7)), frac)
    }

    #[inline]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    fn mul(a: __m512d, b: __m512d) -> __m512d {
        _mm512_mul_pd(a, b)
    }

    #[inline]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    fn add(a: __m512d, b: __m512d) -> __m512d {
        _mm512_add_pd(a, b)
    }

    /// Four consecutive f64 at each of `base + off[l]` (l = 0..8), transposed: out[c][l].
    /// Loads rows instead of gathering element by element (gathers are slow on Zen 4).
    #[inline]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    unsafe fn rows4(base: *const f64, off: &[i32; 8]) -> [__m512d; 4] {
        // SAFETY: the caller's offsets address 4 readable f64 each.
        unsafe {
            let ld = |l: usize| _mm256_loadu_pd(base.offset(off[l] as isize));
            let z0 = _mm512_insertf64x4::<1>(_mm512_castpd256_pd512(ld(0)), ld(4));
            let z1 = _mm512_insertf64x4::<1>(_mm512_castpd256_pd512(ld(1)), ld(5));
            let z2 = _mm512_insertf64x4::<1>(_mm512_castpd256_pd512(ld(2)), ld(6));
            let z3 = _mm512_insertf64x4::<1>(_mm512_castpd256_pd512(ld(3)), ld(7));
            let (t0, t1) = (_mm512_unpacklo_pd(z0, z1), _mm512_unpackhi_pd(z0, z1));
            let (t2, t3) = (_mm512_unpacklo_pd(z2, z3), _mm512_unpackhi_pd(z2, z3));
            let lo = _mm512_setr_epi64(0, 1, 8, 9, 4, 5, 12, 13);
            let hi = _mm512_setr_epi64(2, 3, 10, 11, 6, 7, 14, 15);
            [
                _mm512_permutex2var_pd(t0, lo, t2),
                _mm512_permutex2var_pd(t1, lo, t3),
                _mm512_permutex2var_pd(t0, hi, t2),
                _mm512_permutex2var_pd(t1, hi, t3),
            ]
        }
    }

    /// Seven consecutive f64 at each of `base + off[l]` (8 are read), transposed: out[c][l].
    #[inline]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    unsafe fn rows7(base: *const f64, off: &[i32; 8]) -> [__m512d; 7] {
        // SAFETY: the caller's offsets address 8 readable f64 each.
        unsafe {
            let r: [__m512d; 8] = std::array::from_fn(|l| _mm512_loadu_pd(base.offset(off[l] as isize)));
            let lo = _mm512_setr_epi64(0, 1, 8, 9, 4, 5, 12, 13);
            let hi = _mm512_setr_epi64(2, 3, 10, 11, 6, 7, 14, 15);
            let mut u = [_mm512_setzero_pd(); 8];
            for h in 0..2 {
                let (a, b, c, d) = (r[4 * h], r[4 * h + 1], r[4 * h + 2], r[4 * h + 3]);
                let (t0, t1) = (_mm512_unpacklo_pd(a, b), _mm512_unpackhi_pd(a, b));
                let (t2, t3) = (_mm512_unpacklo_pd(c, d), _mm512_unpackhi_pd(c, d));
                // u[4h + k]: coefficient pair (k, k + 4) of rows 4h..4h + 4.
                u[4 * h] = _mm512_permutex2var_pd(t0, lo, t2);
                u[4 * h + 1] = _mm512_permutex2var_pd(t1, lo, t3);
                u[4 * h + 2] = _mm512_permutex2var_pd(t0, hi, t2);
                u[4 * h + 3] = _mm512_permutex2var_pd(t1, hi, t3);
            }
            [
                _mm512_shuffle_f64x2::<0b01_00_01_00>(u[0], u[4]),
                _mm512_shuffle_f64x2::<0b01_00_01_00>(u[1], u[5]),
                _mm512_shuffle_f64x2::<0b01_00_01_00>(u[2], u[6]),
                _mm512_shuffle_f64x2::<0b01_00_01_00>(u[3], u[7]),
                _mm512_shuffle_f64x2::<0b11_10_11_10>(u[0], u[4]),
                _mm512_shuffle_f64x2::<0b11_10_11_10>(u[1], u[5]),
                _mm512_shuffle_f64x2::<0b11_10_11_10>(u[2], u[6]),
            ]
        }
    }

    /// The periodic image shifts of 8 pairs from their list codes, as [`super::Images`] holds
    /// them: the table lookup where the box has one, else the exact decoding.
    struct Shifts {
        half: __m512d,
        s12: __m512d,
        inv12: __m512d,
        s2: __m512d,
        inv2: __m512d,
        h: [__m512d; 3],
        l: [__m512d; 3],
        lut: Option<[[__m512d; 4]; 3]>,
    }

    impl Shifts {
        #[inline]
        #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
        fn new(img: &super::Images) -> Self {
            Shifts {
                half: _mm512_set1_pd(0.5),
                s12: _mm512_set1_pd(img.s12),
                inv12: _mm512_set1_pd(1.0 / img.s12),
                s2: _mm512_set1_pd(img.s2),
                inv2: _mm512_set1_pd(1.0 / img.s2),
                h: [_mm512_set1_pd(img.h[0]), _mm512_set1_pd(img.h[1]), _mm512_set1_pd(img.h[2])],
                l: [_mm512_set1_pd(img.l[0]), _mm512_set1_pd(img.l[1]), _mm512_set1_pd(img.l[2])],
                // SAFETY: each table holds LUT = 32 f64, read as four 8-lane vectors.
                lut: img
                    .lut
                    .as_ref()
                    .map(|t| t.map(|a| std::array::from_fn::<__m512d, 4, _>(|q| unsafe { _mm512_loadu_pd(a.as_ptr().add(8 * q)) }))),
            }
        }

        /// (sx, sy, sz) of the 8 codes `cv` (each below the box's code count).
        #[inline]
        #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
        fn of(&self, cv: __m256i) -> (__m512d, __m512d, __m512d) {
            if let Some(t) = &self.lut {
                // Table lookup: bit 3 of the index picks the table of a pair, bit 4 the pair.
                let ix = _mm512_cvtepu32_epi64(cv);
                let upper = _mm512_test_epi64_mask(ix, _mm512_set1_epi64(16));
                let look = |t: &[__m512d; 4]| {
                    _mm512_mask_blend_pd(upper, _mm512_permutex2var_pd(t[0], ix, t[1]), _mm512_permutex2var_pd(t[2], ix, t[3]))
                };
                (look(&t[0]), look(&t[1]), look(&t[2]))
            } else {
                // code = ((a + h0) s1 + b + h1) s2 + c + h2, decoded exactly in f64 (< 2^16).
                let (h, l) = (&self.h, &self.l);
                let c = _mm512_cvtepi32_pd(cv);
                let a = _mm512_roundscale_pd::<0x0b>(_mm512_mul_pd(_mm512_add_pd(c, self.half), self.inv12));
                let rest = _mm512_sub_pd(c, _mm512_mul_pd(a, self.s12));
                let b = _mm512_roundscale_pd::<0x0b>(_mm512_mul_pd(_mm512_add_pd(rest, self.half), self.inv2));
                let cc = _mm512_sub_pd(rest, _mm512_mul_pd(b, self.s2));
                // shift = n * L, n exact: the same product as the scalar's shift table.
                (
                    _mm512_mul_pd(_mm512_sub_pd(a, h[0]), l[0]),
                    _mm512_mul_pd(_mm512_sub_pd(b, h[1]), l[1]),
                    _mm512_mul_pd(_mm512_sub_pd(cc, h[2]), l[2]),
                )
            }
        }
    }

    /// Row `i`'s list entries: pairs within the cut-off appended at `np` (in list order).
    /// `x4`: positions padded to 4 f64 per atom; `img`: image decoding of the list's codes.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    ///
    /// `PADDED`: the caller guarantees that the 8 u32 from `js[k]` are readable atoms of the
    /// box for every k < js.len() (the filtered list: later rows' entries, then 8 zeros),
    /// so all 8 row offsets are read straight from `js` (no per-lane loop through memory).
    pub(super) unsafe fn geometry4<const KEEP: bool, const PADDED: bool>(
        xi: [f64; 3],
        js: &[u32],
        codes: &[u16],
        x4: *const f64,
        img: &super::Images,
        n: usize,
        cut2: f64,
        s: &mut Scratch,
        i: usize,
        mut np: usize,
        kb: usize,
    ) -> usize {
        let (x0, x1, x2) = (_mm512_set1_pd(xi[0]), _mm512_set1_pd(xi[1]), _mm512_set1_pd(xi[2]));
        let cut = _mm512_set1_pd(cut2);
        let iv = _mm256_set1_epi32(i as i32);
        let (nmax, cmax) = (_mm256_set1_epi32(n as i32), _mm256_set1_epi32(img.ncodes as i32));
        let shifts = Shifts::new(img);
        let len = js.len();
        let mut k = 0;
        while k < len {
            let rem = (len - k).min(8);
            let lane: __mmask8 = if rem == 8 { 0xff } else { (1u8 << rem) - 1 };
            // SAFETY: masked loads read only the row's entries; atoms and codes are checked
            // below before any load uses them (masked-off lanes are 0, a valid atom and code);
            // stores at np..np + 8 are inside the buffers (np + rem <= list.len()).
            unsafe {
                let jv = _mm256_maskz_loadu_epi32(lane, js.as_ptr().add(k) as *const i32);
                let cv = _mm256_cvtepu16_epi32(_mm_maskz_loadu_epi16(lane, codes.as_ptr().add(k) as *const i16));
                if _mm256_cmpge_epu32_mask(jv, nmax) | _mm256_cmpge_epu32_mask(cv, cmax) != 0 {
                    super::bad_list(n, img.ncodes);
                }
                // Row offsets straight from the list (extracting them from jv costs more).
                let o: [i32; 8] = if PADDED {
                    std::array::from_fn(|l| (*js.as_ptr().add(k + l) as i32) << 2)
                } else {
                    let mut o = [0i32; 8];
                    for l in 0..rem {
                        o[l] = (*js.get_unchecked(k + l) as i32) << 2;
                    }
                    o
                };
                let [xj, yj, zj, _] = rows4(x4, &o);
                let (sx, sy, sz) = shifts.of(cv);
                let dx = _mm512_sub_pd(_mm512_sub_pd(x0, xj), sx);
                let dy = _mm512_sub_pd(_mm512_sub_pd(x1, yj), sy);
                let dz = _mm512_sub_pd(_mm512_sub_pd(x2, zj), sz);
                let r2 = add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz));
                let m = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(lane, r2, cut);
                _mm512_storeu_pd(s.dx.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dx));
                _mm512_storeu_pd(s.dy.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dy));
                _mm512_storeu_pd(s.dz.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dz));
                _mm512_storeu_pd(s.r.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, r2));
                _mm256_storeu_si256(s.j.as_mut_ptr().add(np) as *mut __m256i, _mm256_maskz_compress_epi32(m, jv));
                _mm256_storeu_si256(s.i.as_mut_ptr().add(np) as *mut __m256i, iv);
                if KEEP {
                    // The pairs' list entries (kb + k + lane), for the threaded kernel.
                    let kv = _mm256_add_epi32(_mm256_set1_epi32((kb + k) as i32), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
                    _mm256_storeu_si256(s.k.as_mut_ptr().add(np) as *mut __m256i, _mm256_maskz_compress_epi32(m, kv));
                }
                np += m.count_ones() as usize;
            }
            k += 8;
        }
        np
    }

    /// [`geometry4`] (without list entries) that also filters: the row's entries within
    /// `rin2` appended to `oj` / `oc` (from `no`), the pairs within `cut2` to `s` at `np`.
    /// Returns (np, no).
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    pub(super) unsafe fn geometry4_filter(
        xi: [f64; 3],
        js: &[u32],
        codes: &[u16],
        x4: *const f64,
        img: &super::Images,
        n: usize,
        cut2: f64,
        rin2: f64,
        s: &mut Scratch,
        i: usize,
        mut np: usize,
        oj: *mut u32,
        oc: *mut u16,
        mut no: usize,
    ) -> (usize, usize) {
        let (x0, x1, x2) = (_mm512_set1_pd(xi[0]), _mm512_set1_pd(xi[1]), _mm512_set1_pd(xi[2]));
        let (cut, rin) = (_mm512_set1_pd(cut2), _mm512_set1_pd(rin2));
        let iv = _mm256_set1_epi32(i as i32);
        let (nmax, cmax) = (_mm256_set1_epi32(n as i32), _mm256_set1_epi32(img.ncodes as i32));
        let shifts = Shifts::new(img);
        let len = js.len();
        let mut k = 0;
        while k < len {
            let rem = (len - k).min(8);
            let lane: __mmask8 = if rem == 8 { 0xff } else { (1u8 << rem) - 1 };
            // SAFETY: as `geometry4`; the filtered entries of the row fit the caller's
            // buffers from `no` (at least the row's length plus 8).
            unsafe {
                let jv = _mm256_maskz_loadu_epi32(lane, js.as_ptr().add(k) as *const i32);
                let cv = _mm256_cvtepu16_epi32(_mm_maskz_loadu_epi16(lane, codes.as_ptr().add(k) as *const i16));
                if _mm256_cmpge_epu32_mask(jv, nmax) | _mm256_cmpge_epu32_mask(cv, cmax) != 0 {
                    super::bad_list(n, img.ncodes);
                }
                let mut o = [0i32; 8];
                for l in 0..rem {
                    o[l] = (*js.get_unchecked(k + l) as i32) << 2;
                }
                let [xj, yj, zj, _] = rows4(x4, &o);
                let (sx, sy, sz) = shifts.of(cv);
                let dx = _mm512_sub_pd(_mm512_sub_pd(x0, xj), sx);
                let dy = _mm512_sub_pd(_mm512_sub_pd(x1, yj), sy);
                let dz = _mm512_sub_pd(_mm512_sub_pd(x2, zj), sz);
                let r2 = add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz));
                let mi = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(lane, r2, rin);
                _mm256_storeu_si256(oj.add(no) as *mut __m256i, _mm256_maskz_compress_epi32(mi, jv));
                _mm_storeu_si128(oc.add(no) as *mut __m128i, _mm256_cvtepi32_epi16(_mm256_maskz_compress_epi32(mi, cv)));
                no += mi.count_ones() as usize;
                let m = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(lane, r2, cut);
                _mm512_storeu_pd(s.dx.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dx));
                _mm512_storeu_pd(s.dy.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dy));
                _mm512_storeu_pd(s.dz.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dz));
                _mm512_storeu_pd(s.r.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, r2));
                _mm256_storeu_si256(s.j.as_mut_ptr().add(np) as *mut __m256i, _mm256_maskz_compress_epi32(m, jv));
                _mm256_storeu_si256(s.i.as_mut_ptr().add(np) as *mut __m256i, iv);
                np += m.count_ones() as usize;
            }
            k += 8;
        }
        (np, no)
    }

    /// Row `i`'s list entries: pairs within the cut-off appended at `np` (in list order).
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    pub(super) unsafe fn geometry(
        xi: [f64; 3],
        js: &[u32],
        codes: &[u16],
        xu: *const f64,
        sh: *const f64,
        cut2: f64,
        s: &mut Scratch,
        i: usize,
        mut np: usize,
    ) -> usize {
        let (x0, x1, x2) = (_mm512_set1_pd(xi[0]), _mm512_set1_pd(xi[1]), _mm512_set1_pd(xi[2]));
        let cut = _mm512_set1_pd(cut2);
        let iv = _mm256_set1_epi32(i as i32);
        let len = js.len();
        let mut k = 0;
        while k < len {
            let rem = (len - k).min(8);
            let lane: __mmask8 = if rem == 8 { 0xff } else { (1u8 << rem) - 1 };
            // SAFETY: masked loads read only the row's entries; gathers index xu / sh within
            // bounds (masked-off lanes are 0, a valid atom and code); stores at np..np + 8 are
            // inside the buffers (np + rem <= list.len()).
            unsafe {
                let jv = _mm256_maskz_loadu_epi32(lane, js.as_ptr().add(k) as *const i32);
                let cv = _mm256_cvtepu16_epi32(_mm_maskz_loadu_epi16(lane, codes.as_ptr().add(k) as *const i16));
                let j3 = _mm256_add_epi32(_mm256_add_epi32(jv, jv), jv);
                let c3 = _mm256_add_epi32(_mm256_add_epi32(cv, cv), cv);
                let dx = _mm512_sub_pd(_mm512_sub_pd(x0, gather(j3, xu)), gather(c3, sh));
                let dy = _mm512_sub_pd(_mm512_sub_pd(x1, gather(j3, xu.add(1))), gather(c3, sh.add(1)));
                let dz = _mm512_sub_pd(_mm512_sub_pd(x2, gather(j3, xu.add(2))), gather(c3, sh.add(2)));
                let r2 = add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz));
                let m = _mm512_mask_cmp_pd_mask::<_CMP_LT_OQ>(lane, r2, cut);
                _mm512_storeu_pd(s.dx.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dx));
                _mm512_storeu_pd(s.dy.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dy));
                _mm512_storeu_pd(s.dz.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, dz));
                _mm512_storeu_pd(s.r.as_mut_ptr().add(np), _mm512_maskz_compress_pd(m, r2));
                _mm256_storeu_si256(s.j.as_mut_ptr().add(np) as *mut __m256i, _mm256_maskz_compress_epi32(m, jv));
                _mm256_storeu_si256(s.i.as_mut_ptr().add(np) as *mut __m256i, iv);
                np += m.count_ones() as usize;
            }
            k += 8;
        }
        np
    }

    /// r = sqrt(r^2) in place, the spline offsets and fractions (`m7`, `frac`, kept for
    /// [`force`]) and the density value of pairs q0..q0 + len into blk. Two loops: the
    /// offsets go through memory, so the row loads of the second read them as plain integers.
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    pub(super) unsafe fn density(t: &Tab, s: &mut Scratch, q0: usize, len: usize) {
        let mut k = 0;
        while k < len {
            // SAFETY: q0 + k + 8 <= the padded end of every buffer.
            unsafe {
                let q = q0 + k;
                let r = _mm512_sqrt_pd(_mm512_loadu_pd(s.r.as_ptr().add(q)));
                _mm512_storeu_pd(s.r.as_mut_ptr().add(q), r);
                let (m7, p) = index(r, t);
                _mm256_storeu_si256(s.m7.as_mut_ptr().add(q) as *mut __m256i, m7);
                _mm512_storeu_pd(s.frac.as_mut_ptr().add(q), p);
            }
            k += 8;
        }
        let mut k = 0;
        while k < len {
            // SAFETY: as above; spline rows m <= nr - 1 exist.
            unsafe {
                let q = q0 + k;
                let o = &*(s.m7.as_ptr().add(q) as *const [i32; 8]);
                let p = _mm512_loadu_pd(s.frac.as_ptr().add(q));
                let [c3, c4, c5, c6] = rows4(t.dens.add(3), o);
                let v = add(mul(add(mul(add(mul(c3, p), c4), p), c5), p), c6);
                _mm512_storeu_pd(s.blk.as_mut_ptr().add(k), v);
            }
            k += 8;
        }
    }

    /// Force terms of pairs q0..q0 + len into blk (TERMS arrays of stride bl).
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2")]
    pub(super) unsafe fn force(t: &Tab, s: &mut Scratch, fp: *const f64, q0: usize, len: usize, bl: usize) {
        let one = _mm512_set1_pd(1.0);
        let sign = _mm512_set1_epi64(i64::MIN);
        let mut k = 0;
        while k < len {
            // SAFETY: q0 + k + 8 <= the padded end; i and j index fp; spline rows exist;
            // blk holds TERMS * bl and k + 8 <= bl.
            unsafe {
                let q = q0 + k;
                let r = _mm512_loadu_pd(s.r.as_ptr().add(q));
                // The density pass's spline offsets and fractions (the same bits as `index`).
                let o = &*(s.m7.as_ptr().add(q) as *const [i32; 8]);
                let p = _mm512_loadu_pd(s.frac.as_ptr().add(q));
                let [d0, d1, d2, _] = rows4(t.dens, o);
                let rho_p = add(mul(add(mul(d0, p), d1), p), d2);
                let [z0, z1, z2, z3, z4, z5, z6] = rows7(t.z2, o);
                let z2p = add(mul(add(mul(z0, p), z1), p), z2);
                let z2v = add(mul(add(mul(add(mul(z3, p), z4), p), z5), p), z6);
                let recip = _mm512_div_pd(one, r);
                let phi = mul(z2v, recip);
                let phip = _mm512_sub_pd(mul(z2p, recip), mul(phi, recip));
                let iv = _mm256_loadu_si256(s.i.as_ptr().add(q) as *const __m256i);
                let jv = _mm256_loadu_si256(s.j.as_ptr().add(q) as *const __m256i);
                // Eight pairs span one or two rows (i ascends): two broadcasts and a blend
                // give the gather's values; padding or short rows take the gather.
                let (ia, ib) = (*s.i.get_unchecked(q), *s.i.get_unchecked(q + 7));
                let ma = _mm256_cmpeq_epi32_mask(iv, _mm256_set1_epi32(ia));
                let fpi = if ma | _mm256_cmpeq_epi32_mask(iv, _mm256_set1_epi32(ib)) == 0xff {
                    _mm512_mask_blend_pd(ma, _mm512_set1_pd(*fp.add(ib as usize)), _mm512_set1_pd(*fp.add(ia as usize)))
                } else {
                    gather(iv, fp)
                };
                let fpj = gather(jv, fp);
                let psip = add(add(mul(fpi, rho_p), mul(fpj, rho_p)), phip);
                let neg = _mm512_castsi512_pd(_mm512_xor_si512(_mm512_castpd_si512(psip), sign));
                let fpair = mul(neg, recip);
                let dx = _mm512_loadu_pd(s.dx.as_ptr().add(q));
                let dy = _mm512_loadu_pd(s.dy.as_ptr().add(q));
                let dz = _mm512_loadu_pd(s.dz.as_ptr().add(q));
                let (fx, fy, fz) = (mul(dx, fpair), mul(dy, fpair), mul(dz, fpair));
                let o = s.blk.as_mut_ptr().add(k);
                _mm512_storeu_pd(o, fx);
                _mm512_storeu_pd(o.add(bl), fy);
                _mm512_storeu_pd(o.add(2 * bl), fz);
                _mm512_storeu_pd(o.add(3 * bl), phi);
                _mm512_storeu_pd(o.add(4 * bl), mul(dx, fx));
                _mm512_storeu_pd(o.add(5 * bl), mul(dy, fy));
                _mm512_storeu_pd(o.add(6 * bl), mul(dz, fz));
                _mm512_storeu_pd(o.add(7 * bl), mul(dx, fy));
                _mm512_storeu_pd(o.add(8 * bl), mul(dx, fz));
                _mm512_storeu_pd(o.add(9 * bl), mul(dy, fz));
            }
            k += 8;
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{Scratch, Tab};
    use std::arch::x86_64::*;

    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn gather(idx: __m128i, base: *const f64) -> __m256d {
        // SAFETY: the caller's indices are inside the table at `base`.
        unsafe { _mm256_i32gather_pd::<8>(base, idx) }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn index(r: __m256d, t: &Tab) -> (__m128i, __m256d) {
        let p = _mm256_add_pd(_mm256_mul_pd(r, _mm256_set1_pd(t.rdr)), _mm256_set1_pd(1.0));
        let m = _mm_min_epi32(_mm256_cvttpd_epi32(p), _mm_set1_epi32(t.nr1));
        let frac = _mm256_min_pd(_mm256_sub_pd(p, _mm256_cvtepi32_pd(m)), _mm256_set1_pd(1.0));
        (_mm_mullo_epi32(m, _mm_set1_epi32(7)), frac)
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn mul(a: __m256d, b: __m256d) -> __m256d {
        _mm256_mul_pd(a, b)
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn add(a: __m256d, b: __m256d) -> __m256d {
        _mm256_add_pd(a, b)
    }

    /// Four consecutive f64 at each of `base + off[l]` (l = 0..4), transposed: out[c][l].
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn rows4(base: *const f64, off: [i32; 4]) -> [__m256d; 4] {
        // SAFETY: the caller's offsets address 4 readable f64 each.
        unsafe {
            let ld = |l: usize| _mm256_loadu_pd(base.offset(off[l] as isize));
            let (a0, a1, a2, a3) = (ld(0), ld(1), ld(2), ld(3));
            let (t0, t1) = (_mm256_unpacklo_pd(a0, a1), _mm256_unpackhi_pd(a0, a1));
            let (t2, t3) = (_mm256_unpacklo_pd(a2, a3), _mm256_unpackhi_pd(a2, a3));
            [
                _mm256_permute2f128_pd::<0x20>(t0, t2),
                _mm256_permute2f128_pd::<0x20>(t1, t3),
                _mm256_permute2f128_pd::<0x31>(t0, t2),
                _mm256_permute2f128_pd::<0x31>(t1, t3),
            ]
        }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn offsets(v: __m128i) -> [i32; 4] {
        let mut o = [0i32; 4];
        // SAFETY: o holds 4 i32.
        unsafe { _mm_storeu_si128(o.as_mut_ptr() as *mut __m128i, v) };
        o
    }

    /// As `avx512::geometry4`, 4 lanes.
    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn geometry4<const KEEP: bool>(
        xi: [f64; 3],
        js: &[u32],
        codes: &[u16],
        x4: *const f64,
        img: &super::Images,
        n: usize,
        cut2: f64,
        s: &mut Scratch,
        i: usize,
        mut np: usize,
        kb: usize,
    ) -> usize {
        let (x0, x1, x2) = (_mm256_set1_pd(xi[0]), _mm256_set1_pd(xi[1]), _mm256_set1_pd(xi[2]));
        let cut = _mm256_set1_pd(cut2);
        let half = _mm256_set1_pd(0.5);
        let (s12, inv12, s2, inv2) =
            (_mm256_set1_pd(img.s12), _mm256_set1_pd(1.0 / img.s12), _mm256_set1_pd(img.s2), _mm256_set1_pd(1.0 / img.s2));
        let h = [_mm256_set1_pd(img.h[0]), _mm256_set1_pd(img.h[1]), _mm256_set1_pd(img.h[2])];
        let l = [_mm256_set1_pd(img.l[0]), _mm256_set1_pd(img.l[1]), _mm256_set1_pd(img.l[2])];
        let len = js.len();
        let mut k = 0;
        while k < len {
            let rem = (len - k).min(4);
            let (mut jb, mut cb) = ([0i32; 4], [0i32; 4]);
            for l in 0..rem {
                (jb[l], cb[l]) = (js[k + l] as i32, codes[k + l] as i32);
                if js[k + l] as usize >= n || codes[k + l] as usize >= img.ncodes {
                    super::bad_list(n, img.ncodes);
                }
            }
            // SAFETY: atoms and codes were checked; the scalar stores stay in the buffers.
            unsafe {
                let [xj, yj, zj, _] = rows4(x4, jb.map(|j| 4 * j));
                let c = _mm256_cvtepi32_pd(_mm_loadu_si128(cb.as_ptr() as *const __m128i));
                let a = _mm256_round_pd::<0x0b>(_mm256_mul_pd(_mm256_add_pd(c, half), inv12));
                let rest = _mm256_sub_pd(c, _mm256_mul_pd(a, s12));
                let b = _mm256_round_pd::<0x0b>(_mm256_mul_pd(_mm256_add_pd(rest, half), inv2));
                let cc = _mm256_sub_pd(rest, _mm256_mul_pd(b, s2));
                let sx = _mm256_mul_pd(_mm256_sub_pd(a, h[0]), l[0]);
                let sy = _mm256_mul_pd(_mm256_sub_pd(b, h[1]), l[1]);
                let sz = _mm256_mul_pd(_mm256_sub_pd(cc, h[2]), l[2]);
                let dx = _mm256_sub_pd(_mm256_sub_pd(x0, xj), sx);
                let dy = _mm256_sub_pd(_mm256_sub_pd(x1, yj), sy);
                let dz = _mm256_sub_pd(_mm256_sub_pd(x2, zj), sz);
                let r2 = add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz));
                let mut m = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LT_OQ>(r2, cut)) as u32 & ((1u32 << rem) - 1);
                if m != 0 {
                    let (mut ax, mut ay, mut az, mut ar) = ([0.0; 4], [0.0; 4], [0.0; 4], [0.0; 4]);
                    _mm256_storeu_pd(ax.as_mut_ptr(), dx);
                    _mm256_storeu_pd(ay.as_mut_ptr(), dy);
                    _mm256_storeu_pd(az.as_mut_ptr(), dz);
                    _mm256_storeu_pd(ar.as_mut_ptr(), r2);
                    while m != 0 {
                        let l = m.trailing_zeros() as usize;
                        *s.dx.get_unchecked_mut(np) = ax[l];
                        *s.dy.get_unchecked_mut(np) = ay[l];
                        *s.dz.get_unchecked_mut(np) = az[l];
                        *s.r.get_unchecked_mut(np) = ar[l];
                        *s.j.get_unchecked_mut(np) = jb[l];
                        *s.i.get_unchecked_mut(np) = i as i32;
                        if KEEP {
                            *s.k.get_unchecked_mut(np) = (kb + k + l) as i32;
                        }
                        np += 1;
                        m &= m - 1;
                    }
                }
            }
            k += 4;
        }
        np
    }

    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn geometry(
        xi: [f64; 3],
        js: &[u32],
        codes: &[u16],
        xu: *const f64,
        sh: *const f64,
        cut2: f64,
        s: &mut Scratch,
        i: usize,
        mut np: usize,
    ) -> usize {
        let (x0, x1, x2) = (_mm256_set1_pd(xi[0]), _mm256_set1_pd(xi[1]), _mm256_set1_pd(xi[2]));
        let cut = _mm256_set1_pd(cut2);
        let len = js.len();
        let mut k = 0;
        while k < len {
            let rem = (len - k).min(4);
            // Tails through a zero-padded copy (atom 0 and code 0 are valid indices).
            let (mut jb, mut cb) = ([0u32; 4], [0u32; 4]);
            jb[..rem].copy_from_slice(&js[k..k + rem]);
            for (c, &code) in cb.iter_mut().zip(&codes[k..k + rem]) {
                *c = code as u32;
            }
            // SAFETY: gathers index xu / sh within bounds; the scalar stores below stay in the
            // buffers (np + rem <= list.len()).
            unsafe {
                let jv = _mm_loadu_si128(jb.as_ptr() as *const __m128i);
                let cv = _mm_loadu_si128(cb.as_ptr() as *const __m128i);
                let j3 = _mm_add_epi32(_mm_add_epi32(jv, jv), jv);
                let c3 = _mm_add_epi32(_mm_add_epi32(cv, cv), cv);
                let dx = _mm256_sub_pd(_mm256_sub_pd(x0, gather(j3, xu)), gather(c3, sh));
                let dy = _mm256_sub_pd(_mm256_sub_pd(x1, gather(j3, xu.add(1))), gather(c3, sh.add(1)));
                let dz = _mm256_sub_pd(_mm256_sub_pd(x2, gather(j3, xu.add(2))), gather(c3, sh.add(2)));
                let r2 = add(add(mul(dx, dx), mul(dy, dy)), mul(dz, dz));
                let mut m = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LT_OQ>(r2, cut)) as u32 & ((1u32 << rem) - 1);
                if m != 0 {
                    let (mut ax, mut ay, mut az, mut ar) = ([0.0; 4], [0.0; 4], [0.0; 4], [0.0; 4]);
                    _mm256_storeu_pd(ax.as_mut_ptr(), dx);
                    _mm256_storeu_pd(ay.as_mut_ptr(), dy);
                    _mm256_storeu_pd(az.as_mut_ptr(), dz);
                    _mm256_storeu_pd(ar.as_mut_ptr(), r2);
                    while m != 0 {
                        let l = m.trailing_zeros() as usize;
                        *s.dx.get_unchecked_mut(np) = ax[l];
                        *s.dy.get_unchecked_mut(np) = ay[l];
                        *s.dz.get_unchecked_mut(np) = az[l];
                        *s.r.get_unchecked_mut(np) = ar[l];
                        *s.j.get_unchecked_mut(np) = jb[l] as i32;
                        *s.i.get_unchecked_mut(np) = i as i32;
                        np += 1;
                        m &= m - 1;
                    }
                }
            }
            k += 4;
        }
        np
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn density(t: &Tab, s: &mut Scratch, q0: usize, len: usize) {
        let mut k = 0;
        while k < len {
            // SAFETY: q0 + k + 4 <= the padded end; spline rows m <= nr - 1 exist.
            unsafe {
                let q = q0 + k;
                let r = _mm256_sqrt_pd(_mm256_loadu_pd(s.r.as_ptr().add(q)));
                _mm256_storeu_pd(s.r.as_mut_ptr().add(q), r);
                let (m7, p) = index(r, t);
                let [c3, c4, c5, c6] = rows4(t.dens.add(3), offsets(m7));
                let v = add(mul(add(mul(add(mul(c3, p), c4), p), c5), p), c6);
                _mm256_storeu_pd(s.blk.as_mut_ptr().add(k), v);
            }
            k += 4;
        }
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn force(t: &Tab, s: &mut Scratch, fp: *const f64, q0: usize, len: usize, bl: usize) {
        let one = _mm256_set1_pd(1.0);
        let sign = _mm256_set1_pd(-0.0);
        let mut k = 0;
        while k < len {
            // SAFETY: q0 + k + 4 <= the padded end; i and j index fp; spline rows exist;
            // blk holds TERMS * bl and k + 4 <= bl.
            unsafe {
                let q = q0 + k;
                let r = _mm256_loadu_pd(s.r.as_ptr().add(q));
                let (m7, p) = index(r, t);
                let o = offsets(m7);
                let [d0, d1, d2, _] = rows4(t.dens, o);
                let rho_p = add(mul(add(mul(d0, p), d1), p), d2);
                let [z0, z1, z2, z3] = rows4(t.z2, o);
                let [z4, z5, z6, _] = rows4(t.z2.add(4), o);
                let z2p = add(mul(add(mul(z0, p), z1), p), z2);
                let z2v = add(mul(add(mul(add(mul(z3, p), z4), p), z5), p), z6);
                let recip = _mm256_div_pd(one, r);
                let phi = mul(z2v, recip);
                let phip = _mm256_sub_pd(mul(z2p, recip), mul(phi, recip));
                let iv = _mm_loadu_si128(s.i.as_ptr().add(q) as *const __m128i);
                let jv = _mm_loadu_si128(s.j.as_ptr().add(q) as *const __m128i);
                let fpi = gather(iv, fp);
                let fpj = gather(jv, fp);
                let psip = add(add(mul(fpi, rho_p), mul(fpj, rho_p)), phip);
                let fpair = mul(_mm256_xor_pd(psip, sign), recip);
                let dx = _mm256_loadu_pd(s.dx.as_ptr().add(q));
                let dy = _mm256_loadu_pd(s.dy.as_ptr().add(q));
                let dz = _mm256_loadu_pd(s.dz.as_ptr().add(q));
                let (fx, fy, fz) = (mul(dx, fpair), mul(dy, fpair), mul(dz, fpair));
                let o = s.blk.as_mut_ptr().add(k);
                _mm256_storeu_pd(o, fx);
                _mm256_storeu_pd(o.add(bl), fy);
                _mm256_storeu_pd(o.add(2 * bl), fz);
                _mm256_storeu_pd(o.add(3 * bl), phi);
                _mm256_storeu_pd(o.add(4 * bl), mul(dx, fx));
                _mm256_storeu_pd(o.add(5 * bl), mul(dy, fy));
                _mm256_storeu_pd(o.add(6 * bl), mul(dz, fz));
                _mm256_storeu_pd(o.add(7 * bl), mul(dx, fy));
                _mm256_storeu_pd(o.add(8 * bl), mul(dx, fz));
                _mm256_storeu_pd(o.add(9 * bl), mul(dy, fz));
            }
            k += 4;
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::backend::{BoxSpec, CpuBackend, MdBackend, ReferenceBackend};
    use crate::kernel::{self, BoxMeta, BoxView, DeformMode};
    use crate::lattice::{self, LatticeKind};
    use crate::potential::Potential;
    use std::sync::Arc;

    fn pot(name: &str) -> Potential {
        Potential::from_file(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../md-worker/potentials").join(name)).unwrap()
    }

    /// Forces, energy, virial and F'(rho) of a perturbed lattice box on `path`, as bits.
    fn forces_bits(p: &Potential, cells: [usize; 3], a0: f64, jitter: f64, path: SimdPath) -> Vec<u64> {
        let (mut x, l) = lattice::build_oriented(LatticeKind::Fcc, a0, cells, &crate::Orientation::CUBE).unwrap();
        let n = x.len();
        // A deterministic perturbation, some atoms pushed outside the box (image counters).
        for (k, q) in x.iter_mut().enumerate() {
            for d in 0..3 {
                let h = ((k * 7 + d * 13) as f64 * 0.618_033_988_75).fract() - 0.5;
                q[d] += jitter * h;
            }
        }
        let mut meta = BoxMeta {
            id: 0,
            lo: [0.0; 3],
            l,
            lo_build: [0.0; 3],
            l_build: l,
            mode: DeformMode::Affine,
            seed: 0,
            skin: 1.0,
            step: 0,
            pe: 0.0,
            virial: [0.0; 6],
            rebuilds: 0,
        };
        let types = vec![0u32; n];
        let (mut v, mut f, mut xb, mut img) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n], vec![[0.0; 3]; n], vec![[0i32; 3]; n]);
        let mut list = crate::neighbor::NeighborList::default();
        let mut b =
            BoxView { meta: &mut meta, types: &types, x: &mut x, v: &mut v, f: &mut f, x_build: &mut xb, img: &mut img, list: &mut list };
        kernel::rebuild(p, &mut b);
        // Move atoms a little after the build (pairs near the cut-off, images of moved atoms).
        for (k, q) in b.x.iter_mut().enumerate() {
            q[k % 3] += 0.2 * (((k * 3) as f64 * 0.414_213_562).fract() - 0.5);
        }
        b.meta.l[0] *= 1.01;
        let (mut rho, mut fp) = (Vec::new(), Vec::new());
        kernel::with_simd(path, || kernel::compute_forces(p, &mut b, &mut rho, &mut fp));
        let mut out: Vec<u64> = b.f.iter().flatten().map(|c| c.to_bits()).collect();
        out.push(b.meta.pe.to_bits());
        out.extend(b.meta.virial.map(f64::to_bits));
        out.extend(fp.iter().map(|c| c.to_bits()));
        out
    }

    #[test]
    fn every_supported_path_gives_the_scalar_bits() {
        let paths = SimdPath::supported();
        eprintln!("paths on this CPU: {paths:?}");
        for name in ["Cu_mishin1.eam.alloy", "Cu_u3.eam"] {
            let p = pot(name);
            // 4 atoms (many self images), 32, 108 (the coupled runs' box), 500, a stretched box.
            for (cells, a0, jitter) in
                [([1, 1, 1], 3.615, 0.1), ([2, 2, 2], 3.615, 0.3), ([3, 3, 3], 3.6, 0.5), ([5, 5, 5], 3.615, 0.4), ([4, 3, 2], 4.2, 0.2)]
            {
                let want = forces_bits(&p, cells, a0, jitter, SimdPath::Scalar);
                for &path in &paths {
                    let got = forces_bits(&p, cells, a0, jitter, path);
                    assert!(got == want, "{name}, {cells:?} cells: path {path} differs from scalar");
                }
            }
        }
    }

    /// Trajectory bits of a hot, deforming 500-atom box (both deformation modes) after 300
    /// steps on `path`, and the filtered list's (filters, evaluations) on this thread meanwhile.
    fn trajectory_bits(p: &Potential, mode: DeformMode, path: SimdPath) -> (Vec<u64>, (u64, u64)) {
        let (mut x, l) = lattice::build_oriented(LatticeKind::Fcc, 3.615, [5, 5, 5], &crate::Orientation::CUBE).unwrap();
        let n = x.len();
        for (k, q) in x.iter_mut().enumerate() {
            for d in 0..3 {
                q[d] += 0.1 * (((k * 7 + d * 13) as f64 * 0.618_033_988_75).fract() - 0.5);
            }
        }
        let masses = match p {
            Potential::Eam(t) => t.masses.clone(),
            Potential::LjCut(_) => unreachable!(),
        };
        // 1200 K: atoms move fast, so the filtered list is re-filtered many times per list.
        let mut rng = lattice::rng_for(3, 0, 0, 0);
        let mut v = lattice::maxwell_velocities(&mut rng, &vec![masses[0]; n], 1200.0);
        lattice::remove_momentum(&mut v, &vec![masses[0]; n]);
        let mut meta = BoxMeta {
            id: 0,
            lo: [0.0; 3],
            l,
            lo_build: [0.0; 3],
            l_build: l,
            mode,
            seed: 0,
            skin: 1.0,
            step: 0,
            pe: 0.0,
            virial: [0.0; 6],
            rebuilds: 0,
        };
        let types = vec![0u32; n];
        let (mut f, mut xb, mut img) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n], vec![[0i32; 3]; n]);
        let mut list = crate::neighbor::NeighborList::default();
        let mut b =
            BoxView { meta: &mut meta, types: &types, x: &mut x, v: &mut v, f: &mut f, x_build: &mut xb, img: &mut img, list: &mut list };
        let g = [[0.5, 0.3, 0.0], [0.0, -0.4, 0.2], [0.1, 0.0, 0.3]];
        let g = if mode == DeformMode::Affine { [[0.5, 0.0, 0.0], [0.0, -0.4, 0.0], [0.0, 0.0, 0.3]] } else { g };
        let def = kernel::Deformation::new(mode, &g);
        let before = inner_counts();
        let (mut rho, mut fp) = (Vec::new(), Vec::new());
        kernel::with_simd(path, || {
            kernel::rebuild(p, &mut b);
            kernel::compute_forces(p, &mut b, &mut rho, &mut fp);
            kernel::run_steps(p, &masses, &mut b, &def, 300, 0.002, &mut rho, &mut fp).unwrap();
        });
        let after = inner_counts();
        let mut out: Vec<u64> = b.x.iter().chain(b.v.iter()).chain(b.f.iter()).flatten().map(|c| c.to_bits()).collect();
        out.push(b.meta.pe.to_bits());
        out.extend(b.meta.virial.map(f64::to_bits));
        assert!(b.meta.rebuilds > 3, "the list must be rebuilt a few times: {}", b.meta.rebuilds);
        (out, (after.0 - before.0, after.1 - before.1))
    }

    #[test]
    fn filtered_list_is_reused_and_gives_the_scalar_bits_over_a_hot_run() {
        let p = pot("Cu_mishin1.eam.alloy");
        for mode in [DeformMode::Affine, DeformMode::Seed] {
            let (want, scalar) = trajectory_bits(&p, mode, SimdPath::Scalar);
            assert_eq!(scalar, (0, 0), "the scalar kernel does not filter");
            for path in SimdPath::supported().into_iter().filter(|p| *p != SimdPath::Scalar) {
                let (got, (filters, evals)) = trajectory_bits(&p, mode, path);
                eprintln!("{mode:?} {path}: {filters} filters in {evals} evaluations");
                assert!(got == want, "{mode:?}: path {path} differs from scalar after 300 hot steps");
                // Re-filtered more than once per list build, and reused most of the time.
                assert!(filters > 10 && 2 * filters < evals, "{mode:?} {path}: {filters} filters in {evals} evaluations");
            }
        }
    }

    #[test]
    fn cpu_back_end_on_every_path_matches_reference_bit_for_bit() {
        let p = Arc::new(pot("Cu_mishin1.eam.alloy"));
        let specs: Vec<BoxSpec> = (0..2u64)
            .map(|id| {
                let mut s = BoxSpec::lattice(id, LatticeKind::Fcc, 3.615, [3, 3, 3]);
                s.temperature_k = 600.0;
                s.seed = 7;
                s.relax_steps = 20;
                s
            })
            .collect();
        let work: Vec<_> =
            (0..2u64).map(|id| crate::BoxWork::new(id, [[0.05, 0.0, 0.0], [0.0, -0.02, 0.0], [0.0, 0.0, 0.0]], 60, 0.002)).collect();
        let run = |b: &mut dyn MdBackend| {
            b.open(&specs).unwrap();
            let mut out = vec![crate::BoxResult::default(); 2];
            b.step(&work, &mut out).unwrap();
            let st = b.snapshot(&[0, 1]).unwrap();
            (out, st)
        };
        let want = run(&mut ReferenceBackend::new(p.clone()));
        // The cpu back end takes `selected()` (MSCALE_MD_SIMD, else `best()`): run this
        // test under each value to cover every path.
        let got = run(&mut CpuBackend::new(p.clone()));
        eprintln!("cpu back end path: {}", selected().unwrap());
        let bits = |st: &[crate::BoxState]| -> Vec<u64> {
            st.iter().flat_map(|s| s.x.iter().chain(&s.v).chain(&s.f)).flatten().map(|c| c.to_bits()).collect()
        };
        assert_eq!(got.0, want.0, "results differ from reference");
        assert!(bits(&got.1) == bits(&want.1), "states differ from reference");
    }

    #[test]
    fn parse_names_and_refusals() {
        assert_eq!(SimdPath::parse("scalar").unwrap(), SimdPath::Scalar);
        assert_eq!(SimdPath::parse("auto").unwrap(), SimdPath::best());
        assert_eq!(SimdPath::parse("").unwrap(), SimdPath::best());
        let e = SimdPath::parse("sse9").unwrap_err().to_string();
        assert!(e.contains("MSCALE_MD_SIMD") && e.contains("sse9") && e.contains("expected auto, scalar, avx2 or avx512"), "{e}");
        for p in SimdPath::ALL {
            assert_eq!(SimdPath::parse(p.name()).is_ok(), p.is_supported());
        }
    }
}
