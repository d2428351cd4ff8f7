//! What a pool needs to replace a lost endpoint without touching the others: the log of every
//! input sent to the boxes since the last checkpoint, the deadline of a remote call, the handle
//! that aborts a call on a worker declared lost, and the record of a recovery.
//!
//! Main design decision: a box's evolution is a pure function of its state at a checkpoint and
//! the [`BoxWork`]s it was sent since (velocity gradient, MD steps, MD time step, energy to add,
//! stress sampling; the random numbers come from the box's seed and id and travel in its
//! state). So the pool keeps those inputs in memory, in call order, and a lost endpoint's
//! boxes are rebuilt elsewhere by restoring their checkpoint states and sending them the same
//! inputs again; by the determinism contract they end bitwise where they were. The log is
//! bounded ([`DEFAULT_LOG_LIMIT_BYTES`]); past the bound it is dropped until the next
//! checkpoint and a loss in that window cannot be replayed (the caller falls back to rolling
//! the whole run back to the checkpoint).

use crate::backend::{BoxState, BoxWork, PointId};
use std::sync::Arc;
use std::time::Duration;

/// Default bound of the input log: 256 MiB, about 2.4 million box-calls (a [`BoxWork`] is 112
/// bytes), i.e. 20,000 boxes over 120 continuum steps between checkpoints.
pub const DEFAULT_LOG_LIMIT_BYTES: usize = 256 << 20;

/// The box states of the checkpoint the log starts from, by id (in the order asked). Reads
/// them when a recovery needs them (from the checkpoint file: nothing is kept in memory).
pub type CheckpointBoxes = Arc<dyn Fn(&[PointId]) -> Result<Vec<BoxState>, String> + Send + Sync>;

/// Where the boxes' replay starts.
#[derive(Clone)]
pub enum Baseline {
    /// The boxes as `open` made them (relaxed from their specs): no checkpoint yet.
    Opened,
    /// The checkpoint written at the end of continuum step `step`.
    Checkpoint { step: u64, boxes: CheckpointBoxes },
}

impl Baseline {
    pub fn describe(&self) -> String {
        match self {
            Baseline::Opened => "the boxes as opened (no checkpoint yet)".into(),
            Baseline::Checkpoint { step, .. } => format!("the checkpoint of step {step}"),
        }
    }
}

/// Every input sent to the pool's boxes since [`Baseline`], in call order.
pub struct InputLog {
    pub baseline: Baseline,
    /// (continuum step, the call's work).
    pub calls: Vec<(u64, Vec<BoxWork>)>,
    bytes: usize,
    limit: usize,
    /// Why the log cannot be replayed (it outgrew its bound, boxes were restored without a
    /// checkpoint to start from); cleared by the next checkpoint.
    pub broken: Option<String>,
}

impl Default for InputLog {
    fn default() -> Self {
        InputLog { baseline: Baseline::Opened, calls: Vec::new(), bytes: 0, limit: DEFAULT_LOG_LIMIT_BYTES, broken: None }
    }
}

impl InputLog {
    pub fn set_limit(&mut self, bytes: usize) {
        self.limit = bytes;
    }

    /// Memory the logged calls take (bytes, approximately).
    pub fn bytes(&self) -> usize {
        self.bytes
    }

    /// Appends one call; drops the log when it would pass its bound.
    pub fn record(&mut self, step: u64, work: &[BoxWork]) {
        if self.broken.is_some() {
            return;
        }
        self.bytes += std::mem::size_of_val(work) + std::mem::size_of::<(u64, Vec<BoxWork>)>();
        if self.bytes > self.limit {
            self.broken = Some(format!(
                "the log of the MD inputs since {} outgrew its bound of {:.1} MiB at continuum step {step} (checkpoint more often)",
                self.baseline.describe(),
                self.limit as f64 / (1 << 20) as f64
            ));
            self.calls = Vec::new();
            self.bytes = 0;
            return;
        }
        self.calls.push((step, work.to_vec()));
    }

    /// Starts again from a checkpoint.
    pub fn restart(&mut self, baseline: Baseline) {
        self.baseline = baseline;
        self.calls = Vec::new();
        self.bytes = 0;
        self.broken = None;
    }

    /// The log cannot be replayed until the next checkpoint.
    pub fn invalidate(&mut self, why: String) {
        self.broken = Some(why);
        self.calls = Vec::new();
        self.bytes = 0;
    }
}

/// How long a remote worker may take for one call (a step, open, snapshot or restore) before
/// it is declared lost and its boxes are replayed elsewhere.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum StepDeadline {
    /// max([`StepDeadline::AUTO_MIN`], [`StepDeadline::AUTO_FACTOR`] x the call's expected
    /// time), the expected time from the worker's measured atom-steps per second in this run
    /// (before its first measured call: [`StepDeadline::ASSUMED_ATOM_STEPS_PER_S`]).
    #[default]
    Auto,
    /// The same bound for every call.
    Fixed(Duration),
}

impl StepDeadline {
    pub const AUTO_MIN: Duration = Duration::from_secs(60);
    pub const AUTO_FACTOR: f64 = 10.0;
    /// A slow worker (one core, a heavy potential): 1e5 atom-steps/s.
    pub const ASSUMED_ATOM_STEPS_PER_S: f64 = 1e5;

    /// `auto` or a positive number of seconds.
    pub fn parse(s: &str) -> Result<Self, String> {
        if s.trim() == "auto" {
            return Ok(StepDeadline::Auto);
        }
        match s.trim().parse::<f64>() {
            Ok(v) if v.is_finite() && v > 0.0 && v < 1e9 => Ok(StepDeadline::Fixed(Duration::from_secs_f64(v))),
            _ => Err(format!("step deadline {s:?} is neither `auto` nor a positive number of seconds")),
        }
    }

    /// The deadline of a call of `atom_steps` on a worker that did `measured` atom-steps per
    /// second so far (`None`: nothing measured yet).
    pub fn for_work(&self, atom_steps: f64, measured: Option<f64>) -> Duration {
        match *self {
            StepDeadline::Fixed(d) => d,
            StepDeadline::Auto => {
                let rate = measured.filter(|r| r.is_finite() && *r > 0.0).unwrap_or(Self::ASSUMED_ATOM_STEPS_PER_S);
                let expected = (atom_steps.max(0.0) / rate * Self::AUTO_FACTOR).min(1e7);
                Self::AUTO_MIN.max(Duration::from_secs_f64(expected))
            }
        }
    }
}

impl std::fmt::Display for StepDeadline {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StepDeadline::Auto => write!(f, "auto"),
            StepDeadline::Fixed(d) => write!(f, "{}", d.as_secs_f64()),
        }
    }
}

/// Aborts the calls of one remote endpoint (in flight and later ones): set when the
/// orchestrator declares its worker lost (no heartbeat), so a step never waits on it.
#[derive(Clone)]
pub struct AbortHandle(Arc<tokio::sync::watch::Sender<Option<String>>>);

impl Default for AbortHandle {
    fn default() -> Self {
        AbortHandle(Arc::new(tokio::sync::watch::channel(None).0))
    }
}

impl AbortHandle {
    /// Aborts with a reason (the first one is kept).
    pub fn abort(&self, why: &str) {
        self.0.send_if_modified(|v| {
            if v.is_some() {
                return false;
            }
            *v = Some(why.to_string());
            true
        });
    }

    pub fn reason(&self) -> Option<String> {
        self.0.borrow().clone()
    }

    /// Resolves with the reason once aborted.
    pub async fn aborted(&self) -> String {
        let mut rx = self.0.subscribe();
        match rx.wait_for(Option::is_some).await {
            Ok(v) => v.clone().unwrap_or_default(),
            // The sender lives in `self`: never closed while we wait.
            Err(_) => std::future::pending().await,
        }
    }
}

/// One lost endpoint whose boxes were rebuilt on the survivors.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct Recovery {
    /// The lost endpoint (address).
    pub worker: String,
    /// The continuum step during which it was lost.
    pub step: u64,
    /// What failed.
    pub why: String,
    /// Its boxes, ascending: the only ones restored and replayed.
    pub boxes: Vec<PointId>,
    /// Where they went.
    pub onto: Vec<String>,
    /// What they were restored from.
    pub baseline: String,
    /// Logged calls replayed.
    pub replayed_calls: usize,
    /// Box-calls replayed: one box advanced through one logged call (its MD steps).
    pub replayed_box_steps: u64,
    /// MD steps replayed, summed over the boxes.
    pub replayed_md_steps: u64,
}

impl std::fmt::Display for Recovery {
    /// One line for logs and job notes.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "worker {} was lost at step {} ({}); its {} boxes were restored from {} onto {} and {} box-steps ({} MD steps) replayed",
            self.worker,
            self.step,
            self.why,
            self.boxes.len(),
            self.baseline,
            self.onto.join(", "),
            self.replayed_box_steps,
            self.replayed_md_steps
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadlines_and_the_log_bound() {
        assert_eq!(StepDeadline::parse("auto").unwrap(), StepDeadline::Auto);
        assert_eq!(StepDeadline::parse("2.5").unwrap(), StepDeadline::Fixed(Duration::from_millis(2500)));
        for bad in ["0", "-1", "nan", "soon", ""] {
            assert!(StepDeadline::parse(bad).unwrap_err().contains("neither"), "{bad}");
        }
        assert_eq!(StepDeadline::Auto.for_work(1e3, None), StepDeadline::AUTO_MIN);
        // 1e9 atom-steps at 1e6/s: 1000 s expected, 10x that.
        assert_eq!(StepDeadline::Auto.for_work(1e9, Some(1e6)), Duration::from_secs(10_000));
        assert_eq!(StepDeadline::Fixed(Duration::from_secs(3)).for_work(1e12, Some(1.0)), Duration::from_secs(3));

        let mut log = InputLog::default();
        let w = vec![BoxWork::new(0, [[0.0; 3]; 3], 1, 0.001); 10];
        log.set_limit(3 * (std::mem::size_of_val(&w[..]) + 32));
        log.record(1, &w);
        log.record(2, &w);
        assert_eq!(log.calls.len(), 2);
        log.record(3, &w);
        log.record(4, &w);
        assert!(log.calls.is_empty() && log.broken.as_deref().unwrap().contains("outgrew its bound"), "{:?}", log.broken);
        log.restart(Baseline::Opened);
        log.record(5, &w);
        assert_eq!((log.calls.len(), log.broken.is_none()), (1, true));
    }

    #[test]
    fn an_abort_wakes_a_waiting_call() {
        let h = AbortHandle::default();
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let h2 = h.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(50));
            h2.abort("no heartbeat");
            h2.abort("second");
        });
        assert_eq!(rt.block_on(h.aborted()), "no heartbeat");
        assert_eq!(rt.block_on(h.aborted()), "no heartbeat");
    }
}
