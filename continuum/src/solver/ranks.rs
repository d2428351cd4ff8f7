//! The explicit step's per-point work split over MPI ranks (issue 14 stages 2-4;
//! continuum/README.md "MPI"). Every rank holds an array of every point, but computes only the
//! points of the slab tiles it owns ([`par::Tiles::owner`], the tiles whose scatter buffers it
//! fills; shared out by measured cost, [`LoadBalance`]): their stencil rows, velocity gradients,
//! deformation, closures, viscosity, motion and the guard's check. Only those points are
//! current on the rank: no point state is exchanged at the end of a step
//! ([`Simulation::finish_split`] gathers the wave speed, the tiles' sums and the point counts),
//! a point whose new position lies in another rank's tiles is sent to it whole at the start of
//! the next step ([`Simulation::migrate`]), and [`Simulation::share_all`] shares every point's
//! whole state where all of it is read (outputs, checkpoints, the end).
//! The points a rank computes hold the bits one process computes (each point's update reads
//! only its own state and the nodal fields, which every rank reduces in the same tile order),
//! whatever the number of ranks and the split.
//!
//! A failure on any rank (a point off the grid, an inverted point, a closure error, a
//! non-finite point) is agreed at the phase where it happens: every rank calls [`agree`] after
//! each fallible per-point phase, with its own lowest failing point or none, and every rank
//! returns the error of the lowest point over all ranks (the one a single process reports), so
//! all ranks stop at the same phase of the same step and no collective is left waiting.

use super::*;
use crate::closure::{ClosureError, error_chain as chain};
use crate::par::TileExchange;

/// Points a rank sends per round of [`Simulation::send_points`] by default (about 9 MB of
/// state in 3D); `MSCALE_MPI_SEND_ROUND` sets another count (the tests use a few points to run
/// many rounds).
const SEND_ROUND: usize = 16_384;

fn send_round() -> usize {
    static ROUND: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *ROUND.get_or_init(|| std::env::var("MSCALE_MPI_SEND_ROUND").ok().and_then(|v| v.parse().ok()).filter(|&n| n > 0).unwrap_or(SEND_ROUND))
}

/// Steps between two rebalances of the tiles over the ranks by default.
pub const DEFAULT_REBALANCE_EVERY: u64 = 100;

/// Which rank computes which tiles (the split path over MPI ranks), chosen by measured cost:
/// on the first split step of a process by point counts, then every [`LoadBalance::every`]
/// steps from what the ranks measured since the last choice: a tile costs, per point, the
/// measured seconds of the step's per-point work outside the closures and collectives (one
/// figure over all bodies) plus its body's measured closure seconds per point. Every rank
/// all-gathers the measurements and cuts the same contiguous tile blocks
/// ([`par::balanced_cuts`]), so the split is the same on every rank. The results never depend
/// on the split: every scatter sums in tile order and every point's update reads only its own
/// state and the nodal fields, whichever rank computes it (continuum/README.md "MPI").
#[derive(Debug, Clone)]
pub struct LoadBalance {
    /// Rebalance every this many steps (0: never; the even tile blocks of [`par::tile_owner`]).
    pub every: u64,
    /// How many times the tiles were shared out (0 without a split).
    pub rebalances: u64,
    /// Since the last rebalance, on this rank: the seconds of the split steps outside the
    /// collectives, the points this rank stepped (summed over the steps), and per body the
    /// seconds in its closure and the points it advanced.
    compute_s: f64,
    point_steps: f64,
    body_s: Vec<f64>,
    body_points: Vec<f64>,
}

impl Default for LoadBalance {
    fn default() -> Self {
        LoadBalance {
            every: DEFAULT_REBALANCE_EVERY,
            rebalances: 0,
            compute_s: 0.0,
            point_steps: 0.0,
            body_s: Vec::new(),
            body_points: Vec::new(),
        }
    }
}

impl LoadBalance {
    /// Adds one split step of this rank: `seconds` outside the collectives, `points` stepped.
    pub(super) fn record(&mut self, seconds: f64, points: usize) {
        self.compute_s += seconds;
        self.point_steps += points as f64;
    }
}

impl<const D: usize> Simulation<D> {
    /// The tiles' owners for this step (`self.tiles` just assigned): rebalanced on the first
    /// split step of the process and every [`LoadBalance::every`] steps ([`LoadBalance`]); a
    /// collective, called by every rank at the same step (the condition reads replicated state
    /// only).
    pub(super) fn rebalance(&mut self, ex: &dyn TileExchange) {
        let size = ex.size();
        let lb = &mut self.balance;
        let first = self.tiles.cuts().len() != size + 1;
        if lb.every == 0 || (!first && !self.step.is_multiple_of(lb.every)) {
            return;
        }
        let nb = self.body_ranges.len();
        lb.body_s.resize(nb, 0.0);
        lb.body_points.resize(nb, 0.0);
        let mut mine = vec![lb.compute_s, lb.point_steps];
        mine.extend_from_slice(&lb.body_s);
        mine.extend_from_slice(&lb.body_points);
        // Per tile the points of each body (one more column: points in no body), each point
        // counted by the one rank holding it: after a split step the rank that computed it
        // (its tiles list only those), before one (every point current everywhere) rank 0.
        let nt = self.tiles.count();
        let ends: Vec<usize> = self.body_ranges.iter().map(|r| r.end).collect();
        let mut counts = vec![0.0; nt * (nb + 1)];
        if self.foreign_stale || ex.rank() == 0 {
            for t in 0..nt {
                for &p in self.tiles.points(t) {
                    counts[t * (nb + 1) + ends.partition_point(|&e| e <= p)] += 1.0;
                }
            }
        }
        mine.extend_from_slice(&counts);
        let mut sum = vec![0.0; mine.len()];
        for r in ex.all_gather(&mine) {
            for (s, v) in sum.iter_mut().zip(r) {
                *s += v;
            }
        }
        let (body_s, rest) = sum[2..].split_at(nb);
        let (body_points, counts) = rest.split_at(nb);
        let closures_s: f64 = body_s.iter().sum();
        // Per point: the rest of the step's own work, plus its body's closure. Before any
        // measurement (or when the clock saw nothing): one unit a point.
        let base = if sum[1] > 0.0 && sum[0] > 0.0 { ((sum[0] - closures_s) / sum[1]).max(0.0) } else { 1.0 };
        let per_body: Vec<f64> =
            body_s.iter().zip(body_points).map(|(&s, &n)| base + if n > 0.0 && sum[0] > 0.0 { s / n } else { 0.0 }).collect();
        let cost: Vec<f64> =
            counts.chunks_exact(nb + 1).map(|c| c.iter().zip(per_body.iter().chain([&base])).map(|(n, per)| n * per).sum()).collect();
        self.tiles.set_cuts(par::balanced_cuts(&cost, size));
        let lb = &mut self.balance;
        lb.rebalances += 1;
        (lb.compute_s, lb.point_steps) = (0.0, 0.0);
        lb.body_s.iter_mut().chain(lb.body_points.iter_mut()).for_each(|v| *v = 0.0);
    }

    /// The tiles' split over `ranks` ranks at the last step: the cuts (rank `r` owns tiles
    /// `cuts[r]..cuts[r + 1]`) and the points each rank computed.
    pub fn tile_split(&self, ranks: usize) -> (Vec<usize>, Vec<usize>) {
        let nt = self.tiles.count();
        let owner: Vec<usize> = (0..nt).map(|t| self.tiles.owner(t, ranks)).collect();
        let cuts = (0..=ranks).map(|r| owner.partition_point(|&o| o < r)).collect();
        if self.split_points.len() == ranks {
            // A split step: this rank's tiles hold only its own points; the step's end gathered
            // every rank's count.
            return (cuts, self.split_points.clone());
        }
        let mut points = vec![0; ranks];
        for (t, &r) in owner.iter().enumerate() {
            points[r] += self.tiles.points(t).len();
        }
        (cuts, points)
    }

    /// The exchange to split this step's per-point work over: set over more than one rank and
    /// the step [`Simulation::splittable`]. Otherwise `None`: every rank computes every point
    /// (replicated, stage 1; only the scatters are split).
    pub(super) fn split_ranks(&self) -> Option<&'static dyn TileExchange> {
        let ex = par::exchange().filter(|e| e.size() > 1)?;
        self.splittable().then_some(ex)
    }

    /// Whether the step's per-point work can be split over MPI ranks: its per-point passes
    /// read only their own point and the nodal fields (the explicit integrators, no gradient
    /// correction, nullspace filter, diffusion, IMPM or improved CPDI, closures that are
    /// pointwise).
    pub fn splittable(&self) -> bool {
        let explicit =
            matches!(self.integrator, TimeIntegrator::Dhakal | TimeIntegrator::Leapfrog | TimeIntegrator::Usl | TimeIntegrator::Usf);
        let scheme = !self.scheme.maps_velocity_by_mls();
        let extras = self.gradient_correction == GradientCorrection::None
            && self.nullspace_filter == NullspaceFilter::None
            && self.diffusion.is_none();
        let closures = self.closures.iter().all(|c| c.repeatable());
        explicit && scheme && extras && closures
    }

    /// Values per point in [`Simulation::share_points`].
    fn shared_per_point(&self) -> usize {
        let plastic = usize::from(!self.points.plastic_strain.is_empty());
        // x, v, corners, F, V, L, sigma, q, q_p, e, plastic strain.
        D + D + (1 << D) * D + 9 + 1 + 9 + 9 + 9 + 1 + 1 + plastic
    }

    /// Appends point `p`'s whole end-of-step state to `pack` ([`Simulation::shared_per_point`]
    /// values).
    fn pack_point(&self, p: usize, pack: &mut Vec<f64>) {
        let pts = &self.points;
        let nc = 1usize << D;
        pack.extend_from_slice(&pts.x[p]);
        pack.extend_from_slice(&pts.v[p]);
        for c in &pts.corners[p * nc..(p + 1) * nc] {
            pack.extend_from_slice(c);
        }
        pack.extend(pts.def_grad[p].iter().flatten());
        pack.push(pts.volume[p]);
        pack.extend(pts.vel_grad[p].iter().flatten());
        pack.extend(pts.stress[p].iter().flatten());
        pack.extend(pts.visc_stress[p].iter().flatten());
        pack.push(pts.visc_pressure[p]);
        pack.push(pts.internal_energy[p]);
        if !pts.plastic_strain.is_empty() {
            pack.push(pts.plastic_strain[p]);
        }
    }

    /// Sets point `p`'s whole state from `v`, as [`Simulation::pack_point`] wrote it.
    fn unpack_point(&mut self, p: usize, v: &[f64]) {
        let pts = &mut self.points;
        let nc = 1usize << D;
        let mat = |v: &[f64]| -> Mat3 { std::array::from_fn(|i| std::array::from_fn(|j| v[3 * i + j])) };
        let mut o = 0;
        let mut take = |n: usize| {
            let s = &v[o..o + n];
            o += n;
            s
        };
        let s = take(D);
        pts.x[p] = std::array::from_fn(|a| s[a]);
        let s = take(D);
        pts.v[p] = std::array::from_fn(|a| s[a]);
        for c in &mut pts.corners[p * nc..(p + 1) * nc] {
            let s = take(D);
            *c = std::array::from_fn(|a| s[a]);
        }
        pts.def_grad[p] = mat(take(9));
        pts.volume[p] = take(1)[0];
        pts.vel_grad[p] = mat(take(9));
        pts.stress[p] = mat(take(9));
        pts.visc_stress[p] = mat(take(9));
        pts.visc_pressure[p] = take(1)[0];
        pts.internal_energy[p] = take(1)[0];
        if !pts.plastic_strain.is_empty() {
            pts.plastic_strain[p] = take(1)[0];
        }
    }

    /// Gives every rank every point's state: each rank sends the points it holds (ascending
    /// index) and takes the others'; the tiles then list every point again, as on one process.
    pub(super) fn share_points(&mut self, ex: &dyn TileExchange) {
        let mine: Vec<usize> = (0..self.points.len()).filter(|&p| self.held[p]).collect();
        let mut tile: Vec<Option<usize>> = (0..self.points.len()).map(|p| self.tiles.tile_of(p)).collect();
        self.send_points(ex, &mine, |sim, _, p, t, state| {
            tile[p] = t;
            sim.unpack_point(p, state);
        });
        let n_tiles = self.tiles.count();
        self.tiles.assign_some(n_tiles, tile.len(), |p| tile[p]);
    }

    /// Sends the whole state of `points` (this rank's) to every rank, each point with its index
    /// and its tile of the step, in rounds of at most [`send_round`] points a rank (one
    /// all-gather a round, every rank taking part until no rank has more), so an exchange's
    /// buffers stay a few MB whatever the number of points; calls `take(self, rank, point,
    /// tile, state)` for each point every other rank sent, in that rank's order.
    fn send_points(
        &mut self,
        ex: &dyn TileExchange,
        points: &[usize],
        mut take: impl FnMut(&mut Self, usize, usize, Option<usize>, &[f64]),
    ) {
        let per = 2 + self.shared_per_point();
        let mut next = 0;
        loop {
            let end = (next + send_round()).min(points.len());
            let mut pack = vec![if end < points.len() { 1.0 } else { 0.0 }];
            for &p in &points[next..end] {
                pack.extend([p as f64, self.tiles.tile_of(p).map_or(-1.0, |t| t as f64)]);
                self.pack_point(p, &mut pack);
            }
            next = end;
            let all = ex.all_gather(&pack);
            for (r, buf) in all.iter().enumerate().filter(|(r, _)| *r != ex.rank()) {
                for v in buf[1..].chunks_exact(per) {
                    take(self, r, v[0] as usize, (v[1] >= 0.0).then_some(v[1] as usize), &v[2..]);
                }
            }
            if all.iter().all(|b| b[0] == 0.0) {
                return;
            }
        }
    }

    /// The end of a split step: instead of other ranks' points, every rank gets what the next
    /// step and the per-step figures read of them, in one small all-gather: each rank's largest
    /// wave speed over its points (each body's over all points is the largest of them:
    /// [`Closure::wave_speed`]), the sums of its tiles ([`Simulation::step_totals`], added in
    /// tile order here), its point count; and, in 1D under the neighbour-gap guard, its points'
    /// positions. The rest of other ranks' points stays stale here until
    /// [`Simulation::share_all`], or until a point enters this rank's tiles
    /// ([`Simulation::migrate`]).
    pub(super) fn finish_split(&mut self, ex: &dyn TileExchange) {
        let (rank, size) = (ex.rank(), ex.size());
        let gaps = self.gap_guarded();
        let owned = &self.owned;
        let mut wave = 0.0f64;
        for (range, closure) in self.body_ranges.iter().zip(&self.closures).filter(|(r, _)| r.is_empty() && rank == 0) {
            wave = wave.max(closure.wave_speed(&self.points.mass[range.clone()], &self.points.volume[range.clone()]));
        }
        for (b, run) in owned_runs(&self.body_ranges, owned) {
            wave = wave.max(self.closures[b].wave_speed(&self.points.mass[run.clone()], &self.points.volume[run]));
        }
        let mine: Vec<usize> = (0..self.points.len()).filter(|&p| owned[p]).collect();
        let tiles: Vec<usize> = self.tiles.owned_by(rank, size).collect();
        let mut pack = vec![wave, mine.len() as f64, tiles.len() as f64];
        for &t in &tiles {
            let (sums, scale) = self.tile_sums(t);
            pack.extend([t as f64, sums.mass, sums.kinetic, sums.internal, scale]);
            pack.extend(sums.momentum);
        }
        if gaps {
            for &p in &mine {
                pack.push(p as f64);
                pack.extend(self.points.x[p]);
            }
        }
        let all = ex.all_gather(&pack);
        let mut tile_sums = vec![(Totals::default(), 0.0); self.tiles.count()];
        self.split_points.clear();
        self.split_wave_speed = 0.0;
        for (r, buf) in all.iter().enumerate() {
            self.split_wave_speed = self.split_wave_speed.max(buf[0]);
            self.split_points.push(buf[1] as usize);
            let n_tiles = buf[2] as usize;
            let (sums, rest) = buf[3..].split_at(n_tiles * (5 + D));
            for v in sums.chunks_exact(5 + D) {
                let t = Totals { mass: v[1], momentum: std::array::from_fn(|a| v[5 + a]), kinetic: v[2], internal: v[3] };
                tile_sums[v[0] as usize] = (t, v[4]);
            }
            if gaps && r != rank {
                for v in rest.chunks_exact(1 + D) {
                    self.points.x[v[0] as usize] = std::array::from_fn(|a| v[1 + a]);
                }
            }
        }
        self.step_sums = Some(super::in_tile_order(tile_sums.into_iter()));
        self.held.clone_from(&self.owned);
        self.foreign_stale = true;
    }

    /// The start of a split step after [`Simulation::finish_split`] (`self.tiles` holding the
    /// points this rank computed last step, the owners of this step set): the points in other
    /// ranks' tiles are sent whole (tile by tile, ascending index), every rank takes those that
    /// enter its own tiles, and the tiles are sorted again over the points this rank now holds.
    pub(super) fn migrate(&mut self, ex: &dyn TileExchange) {
        let (rank, size) = (ex.rank(), ex.size());
        let leaving: Vec<usize> = (0..self.tiles.count())
            .filter(|&t| self.tiles.owner(t, size) != rank)
            .flat_map(|t| self.tiles.points(t).iter().copied())
            .collect();
        self.migrated_points += leaving.len() as u64;
        self.send_points(ex, &leaving, |sim, _, p, _, state| {
            sim.migrated_points += 1;
            let x: [f64; D] = std::array::from_fn(|a| state[a]);
            if sim.tiles.owner(par::slab_tile(&sim.grid, &x), size) == rank {
                sim.unpack_point(p, state);
                sim.held[p] = true;
            }
        });
        for &p in &leaving {
            self.held[p] = false;
        }
        let (grid, x, held) = (&self.grid, &self.points.x, &self.held);
        self.tiles.assign_some(par::slab_tile_count(grid), x.len(), |p| held[p].then(|| par::slab_tile(grid, &x[p])));
    }

    /// Makes every point's whole state current on every rank (after split steps, the points a
    /// rank did not compute are stale there): a collective when
    /// anything is stale, so every rank calls it at the same point of the run (before reading
    /// stresses or deformation of all points: outputs, checkpoints, scores, the digest).
    /// Nothing to do on one process or when nothing is stale.
    pub fn share_all(&mut self) {
        if !self.foreign_stale {
            return;
        }
        if let Some(ex) = par::exchange().filter(|e| e.size() > 1) {
            self.share_points(ex);
        }
        self.foreign_stale = false;
    }
}

/// The maximal runs of consecutive `owned` points of each body, with the body's index, in body
/// then point order.
fn owned_runs(body_ranges: &[std::ops::Range<usize>], owned: &[bool]) -> Vec<(usize, std::ops::Range<usize>)> {
    let mut runs = Vec::new();
    for (b, range) in body_ranges.iter().enumerate() {
        let mut p = range.start;
        while p < range.end {
            if !owned[p] {
                p += 1;
                continue;
            }
            let start = p;
            while p < range.end && owned[p] {
                p += 1;
            }
            runs.push((b, start..p));
        }
    }
    runs
}

/// Advances this rank's points (`owned`) of every body, each maximal run of consecutive owned
/// points of a body as one batch (the closures are pointwise: [`Simulation::split_ranks`]
/// admits only repeatable ones). Every batch is prepared before any is advanced, as on one
/// process. On failure: the start of the first failing run (a key that orders failures over
/// ranks as their points do, the runs being disjoint) and the error.
/// Also adds, per body, the seconds its batches took and their points to `balance` (the
/// measured closure cost the tiles are balanced by).
#[allow(clippy::too_many_arguments)]
pub(super) fn advance_owned_closures<const D: usize>(
    pts: &mut Particles<D>,
    closures: &mut [Box<dyn Closure>],
    body_ranges: &[std::ops::Range<usize>],
    owned: &[bool],
    step: u64,
    dt: f64,
    evaluations: &mut u64,
    balance: &mut LoadBalance,
) -> Result<(), (usize, SolverError)> {
    let runs = owned_runs(body_ranges, owned);
    balance.body_s.resize(body_ranges.len(), 0.0);
    balance.body_points.resize(body_ranges.len(), 0.0);
    for prepare in [true, false] {
        for (b, run) in &runs {
            let clock = std::time::Instant::now();
            let batch = pts.batch(step, run.clone());
            let r = if prepare { closures[*b].prepare(&batch, dt) } else { closures[*b].advance(batch, dt) };
            balance.body_s[*b] += clock.elapsed().as_secs_f64();
            if !prepare {
                balance.body_points[*b] += run.len() as f64;
            }
            r.map_err(|source| (run.start, SolverError::Closure { step, source }))?;
        }
    }
    // The count of one process: every point of every body.
    for range in body_ranges {
        *evaluations = evaluations.saturating_add(range.len() as u64);
    }
    Ok(())
}

/// Prepares, then advances over `dt` (`None`: initializes) every body's closure over its whole
/// batch, as one process does, adding the advanced points to `evaluations`. Over the ranks of
/// `ex` (the process's exchange, [`par::exchange`], when set over more than one rank) a closure that is [`Closure::computed_once`] (the MD closure) is called on rank 0
/// only: the ranks agree on the outcome (rank 0's failure stops every rank with its message),
/// then rank 0's stresses (and plastic strains) of those bodies are all-gathered (rank 0 the
/// only sender) into every rank's points. Every other closure runs on every rank (replicated).
pub(super) fn advance_all_closures<const D: usize>(
    ex: Option<&dyn TileExchange>,
    pts: &mut Particles<D>,
    closures: &mut [Box<dyn Closure>],
    body_ranges: &[std::ops::Range<usize>],
    step: u64,
    dt: Option<f64>,
    evaluations: &mut u64,
) -> Result<(), SolverError> {
    let once = ex.filter(|e| e.size() > 1).filter(|_| closures.iter().any(|c| c.computed_once()));
    let skip = |c: &dyn Closure| once.is_some_and(|ex| ex.rank() != 0 && c.computed_once());
    let n = pts.len();
    let mut local = Ok(());
    'passes: for (pass, prepare) in [true, false].into_iter().enumerate() {
        for (b, range) in body_ranges.iter().enumerate() {
            let closure = &mut closures[b];
            let r = if skip(closure.as_ref()) {
                Ok(())
            } else {
                let batch = pts.batch(step, range.clone());
                match (prepare, dt) {
                    (true, _) => closure.prepare(&batch, dt.unwrap_or(0.0)),
                    (false, Some(dt)) => closure.advance(batch, dt),
                    (false, None) => closure.initialize(batch),
                }
            };
            if let Err(source) = r {
                // The order one process meets failures in: the prepare pass, then the advance
                // pass, each in body order.
                local = Err((pass * n + range.start, SolverError::Closure { step, source }));
                break 'passes;
            }
            if !prepare {
                *evaluations = evaluations.saturating_add(range.len() as u64);
            }
        }
    }
    let Some(ex) = once else {
        return local.map_err(|(_, e)| e);
    };
    agree(Some(ex), local)?;
    let plastic = !pts.plastic_strain.is_empty();
    let bodies: Vec<std::ops::Range<usize>> =
        body_ranges.iter().zip(closures.iter()).filter(|(_, c)| c.computed_once()).map(|(r, _)| r.clone()).collect();
    let mut pack = Vec::new();
    if ex.rank() == 0 {
        for p in bodies.iter().flat_map(|r| r.clone()) {
            pack.extend(pts.stress[p].iter().flatten());
            if plastic {
                pack.push(pts.plastic_strain[p]);
            }
        }
    }
    let all = ex.all_gather(&pack);
    if ex.rank() != 0 {
        let per = 9 + usize::from(plastic);
        let from = &all[0];
        let count: usize = bodies.iter().map(|r| r.len()).sum();
        assert_eq!(from.len(), count * per, "rank 0 sent {} values for {count} points of computed-once closures", from.len());
        for (k, p) in bodies.iter().flat_map(|r| r.clone()).enumerate() {
            let v = &from[k * per..(k + 1) * per];
            pts.stress[p] = std::array::from_fn(|i| std::array::from_fn(|j| v[3 * i + j]));
            if plastic {
                pts.plastic_strain[p] = v[9];
            }
        }
    }
    Ok(())
}

/// Agrees over the ranks of `ex` on the outcome of a per-point phase: `local` is this rank's
/// lowest failing point (a key ordering failures as one process meets them) and its error.
/// Every rank gets the error of the lowest key over all ranks, or `Ok` when no rank failed.
/// Without `ex` (one process), `local`'s error as it is.
pub(super) fn agree(ex: Option<&dyn TileExchange>, local: Result<(), (usize, SolverError)>) -> Result<(), SolverError> {
    let Some(ex) = ex else {
        return local.map_err(|(_, e)| e);
    };
    let mine = match &local {
        Ok(()) => Vec::new(),
        Err((key, e)) => encode(*key, e),
    };
    let all = ex.all_gather_bytes(&mine);
    let lowest = all.iter().enumerate().filter(|(_, b)| !b.is_empty()).min_by_key(|(r, b)| (key_of(b), *r));
    match lowest {
        None => Ok(()),
        Some((r, _)) if r == ex.rank() => local.map_err(|(_, e)| e),
        Some((_, b)) => Err(decode(b)),
    }
}

fn key_of(b: &[u8]) -> u64 {
    u64::from_le_bytes(b[..8].try_into().expect("8 bytes"))
}

/// `[key u64][kind u8][step u64][len u32][what][len u32][cause]`: kind 0 a divergence (what,
/// cause), 1 a closure's failure (its error's chain, no cause).
fn encode(key: usize, e: &SolverError) -> Vec<u8> {
    let (kind, step, what, cause) = match e {
        SolverError::Diverged { step, what, cause } => (0u8, *step, what.clone(), cause.to_string()),
        SolverError::Closure { step, source } => (1u8, *step, chain(source), String::new()),
    };
    let mut b = Vec::new();
    b.extend((key as u64).to_le_bytes());
    b.push(kind);
    b.extend(step.to_le_bytes());
    for s in [what, cause] {
        b.extend((s.len() as u32).to_le_bytes());
        b.extend(s.into_bytes());
    }
    b
}

/// The error another rank encoded ([`encode`]).
fn decode(b: &[u8]) -> SolverError {
    let step = u64::from_le_bytes(b[9..17].try_into().expect("8 bytes"));
    let mut k = 17;
    let mut text = || {
        let n = u32::from_le_bytes(b[k..k + 4].try_into().expect("4 bytes")) as usize;
        let s = String::from_utf8_lossy(&b[k + 4..k + 4 + n]).into_owned();
        k += 4 + n;
        s
    };
    let (what, cause) = (text(), text());
    match b[8] {
        // The cause of a divergence is a fixed text; the run stops here, so leaking the one
        // copy received is harmless.
        0 => SolverError::Diverged { step, what, cause: Box::leak(cause.into_boxed_str()) },
        _ => SolverError::Closure { step, source: ClosureError::Other(what) },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::closure::ClosureBatch;

    /// One rank of a pretend exchange: the other ranks' contributions are given.
    struct Fake {
        rank: usize,
        theirs: Vec<Vec<u8>>,
    }

    impl TileExchange for Fake {
        fn rank(&self) -> usize {
            self.rank
        }
        fn size(&self) -> usize {
            self.theirs.len()
        }
        fn all_gather(&self, _: &[f64]) -> Vec<Vec<f64>> {
            unreachable!("agree gathers bytes only")
        }
        fn all_gather_bytes(&self, mine: &[u8]) -> Vec<Vec<u8>> {
            let mut all = self.theirs.clone();
            all[self.rank] = mine.to_vec();
            all
        }
    }

    fn diverged(p: usize) -> SolverError {
        SolverError::Diverged { step: 5, what: format!("particle {p} left the grid"), cause: "a cause" }
    }

    #[test]
    fn every_rank_gets_the_error_of_the_lowest_failing_point() {
        let closure = SolverError::Closure { step: 5, source: ClosureError::NonFinite { point: 3, law: "neo-hookean", jacobian: -1.0 } };
        let want = chain(&closure);
        let (c3, d7) = (encode(3, &closure), encode(7, &diverged(7)));
        // Rank 1 failed at point 7, rank 0 at point 3 (a closure), rank 2 not at all: rank 1
        // and rank 2 report rank 0's error, message for message.
        for rank in [1, 2] {
            let ex = Fake { rank, theirs: vec![c3.clone(), d7.clone(), Vec::new()] };
            let local = if rank == 1 { Err((7, diverged(7))) } else { Ok(()) };
            let e = agree(Some(&ex), local).expect_err("rank 0 failed");
            assert_eq!(chain(&e), want, "rank {rank}");
            assert!(matches!(e, SolverError::Closure { step: 5, .. }), "{e:?}");
        }
        // Rank 0 keeps its own error (its type and source intact).
        let ex = Fake { rank: 0, theirs: vec![Vec::new(), d7.clone(), Vec::new()] };
        let e = agree(Some(&ex), Err((3, closure))).expect_err("failed");
        assert!(matches!(e, SolverError::Closure { source: ClosureError::NonFinite { point: 3, .. }, .. }), "{e:?}");
        // A divergence crosses ranks whole.
        let ex = Fake { rank: 2, theirs: vec![Vec::new(), d7.clone(), Vec::new()] };
        let e = agree(Some(&ex), Ok(())).expect_err("rank 1 failed");
        assert_eq!(chain(&e), chain(&diverged(7)));
        // No failure anywhere: every rank goes on.
        let ex = Fake { rank: 1, theirs: vec![Vec::new(); 3] };
        assert!(agree(Some(&ex), Ok(())).is_ok());
    }

    /// One rank of a pretend exchange for [`advance_all_closures`]: the others' values given.
    struct Pretend {
        rank: usize,
        floats: Vec<Vec<f64>>,
        bytes: Vec<Vec<u8>>,
    }

    impl TileExchange for Pretend {
        fn rank(&self) -> usize {
            self.rank
        }
        fn size(&self) -> usize {
            self.floats.len()
        }
        fn all_gather(&self, mine: &[f64]) -> Vec<Vec<f64>> {
            let mut all = self.floats.clone();
            all[self.rank] = mine.to_vec();
            all
        }
        fn all_gather_bytes(&self, mine: &[u8]) -> Vec<Vec<u8>> {
            let mut all = self.bytes.clone();
            all[self.rank] = mine.to_vec();
            all
        }
    }

    /// Counts its calls and writes `value` into every stress component.
    struct Counting {
        once: bool,
        value: f64,
        calls: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    }

    impl Closure for Counting {
        fn name(&self) -> &'static str {
            "counting"
        }
        fn wave_speed(&self, _: &[f64], _: &[f64]) -> f64 {
            1.0
        }
        fn prepare(&mut self, _: &ClosureBatch<'_>, _: f64) -> Result<(), ClosureError> {
            self.calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            Ok(())
        }
        fn advance(&mut self, b: ClosureBatch<'_>, _: f64) -> Result<(), ClosureError> {
            self.calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            b.stress.iter_mut().for_each(|s| *s = [[self.value; 3]; 3]);
            Ok(())
        }
        fn computed_once(&self) -> bool {
            self.once
        }
    }

    #[test]
    fn a_closure_computed_once_runs_on_rank_0_only_and_every_rank_gets_its_stresses() {
        // Two bodies of two points: body 0's closure is computed once (as the MD closure),
        // body 1's is pointwise. Rank 0 calls both; rank 1 calls only body 1's and takes
        // body 0's stresses from rank 0's gather.
        let points = || {
            let mut pts = Particles::<1>::default();
            for (b, x) in [(0, 0.1), (0, 0.2), (1, 0.3), (1, 0.4)] {
                pts.push(b, [x], [0.0], 1.0, 0.1, [0.05], Particles::<1>::identity());
            }
            pts
        };
        let run = |ex: &Pretend, once_value: f64| {
            let (once, other) = (std::sync::Arc::default(), std::sync::Arc::default());
            let mut closures: Vec<Box<dyn Closure>> = vec![
                Box::new(Counting { once: true, value: once_value, calls: std::sync::Arc::clone(&once) }),
                Box::new(Counting { once: false, value: 2.0, calls: std::sync::Arc::clone(&other) }),
            ];
            let mut pts = points();
            let ranges = pts.body_ranges();
            let mut evaluations = 0;
            advance_all_closures(Some(ex), &mut pts, &mut closures, &ranges, 1, Some(1e-3), &mut evaluations).expect("no failure");
            let load = |c: &std::sync::Arc<std::sync::atomic::AtomicUsize>| c.load(std::sync::atomic::Ordering::Relaxed);
            (pts, load(&once), load(&other), evaluations)
        };
        // Rank 0: both closures called (prepare and advance), its stresses of body 0 sent.
        let ex0 = Pretend { rank: 0, floats: vec![Vec::new(); 2], bytes: vec![Vec::new(); 2] };
        let (pts0, once0, other0, ev0) = run(&ex0, 1.0);
        assert_eq!((once0, other0, ev0), (2, 2, 4));
        assert_eq!(pts0.stress[0], [[1.0; 3]; 3]);
        // Rank 1: the computed-once closure is never called (its own value 9 never appears);
        // body 0's stresses are rank 0's, body 1's its own.
        let sent: Vec<f64> = (0..2).flat_map(|_| [1.0; 9]).collect();
        let ex1 = Pretend { rank: 1, floats: vec![sent, Vec::new()], bytes: vec![Vec::new(); 2] };
        let (pts1, once1, other1, ev1) = run(&ex1, 9.0);
        assert_eq!((once1, other1, ev1), (0, 2, 4), "rank 1 calls only the pointwise closure; counts as one process");
        assert_eq!(pts1.stress, pts0.stress, "every rank holds rank 0's stresses");
        // A failure of rank 0's computed-once closure reaches rank 1, which did not call it.
        let failed = encode(0, &SolverError::Closure { step: 1, source: ClosureError::Other("MD at continuum step 1: box 3".into()) });
        let ex1 = Pretend { rank: 1, floats: vec![Vec::new(); 2], bytes: vec![failed, Vec::new()] };
        let (mut closures, mut pts) = (
            vec![
                Box::new(Counting { once: true, value: 9.0, calls: Default::default() }) as Box<dyn Closure>,
                Box::new(Counting { once: false, value: 2.0, calls: Default::default() }),
            ],
            points(),
        );
        let ranges = pts.body_ranges();
        let e = advance_all_closures(Some(&ex1), &mut pts, &mut closures, &ranges, 1, Some(1e-3), &mut 0).expect_err("rank 0 failed");
        assert!(matches!(e, SolverError::Closure { step: 1, .. }), "{e:?}");
        assert!(chain(&e).ends_with("MD at continuum step 1: box 3"), "{}", chain(&e));
    }
}
