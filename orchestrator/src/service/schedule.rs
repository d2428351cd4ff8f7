//! Which queued job starts next, and on which workers: jobs run side by side on disjoint sets
//! of workers.
//!
//! The queue is ordered by priority (higher first), then by fair share (the user with fewer
//! jobs running first), then by submission. Going down it, a job starts when what it needs
//! is free: its number of workers of one back end and precision (all free ones for `all`;
//! never more than the pool has), or, for a scene without MD or a pool without workers, the
//! one in-process slot (such jobs run one at a time in the orchestrator's process, as before
//! jobs ran side by side). A job that cannot start holds back the jobs after it from what it
//! waits for (workers, or the slot): a worker a running job releases goes to the first job in
//! the queue that waits for workers, so a high-priority job is not overtaken by smaller ones.
//! There is no preemption: running jobs keep their workers until they end.

use super::store::{JobRecord, WorkerRecord};
use std::collections::{BTreeMap, HashMap};

/// What a queued job needs to start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Needs {
    /// The in-process slot (no MD, or MD with no worker registered).
    InProcess,
    /// Workers (0: every free one of a kind).
    Workers(u32),
}

/// Where a job starts.
#[derive(Debug, Clone)]
pub(crate) enum Placement {
    InProcess,
    Workers(Vec<WorkerRecord>),
}

/// The queue in the order jobs are considered: priority (higher first), then the owner with
/// fewer jobs running or ahead of it in this order, then submission order (`queued` comes in
/// priority and submission order).
pub(crate) fn order(mut queued: Vec<JobRecord>, running_per_owner: &HashMap<String, usize>) -> Vec<JobRecord> {
    // Jobs of one owner keep their order; between owners of one priority, the one with fewer
    // running (counting the jobs placed before it in this order) goes first.
    let mut placed: HashMap<String, usize> = running_per_owner.clone();
    let mut out = Vec::with_capacity(queued.len());
    while !queued.is_empty() {
        let top = queued[0].priority;
        let (k, _) = queued
            .iter()
            .enumerate()
            .filter(|(_, j)| j.priority == top)
            .min_by_key(|(k, j)| (placed.get(&j.owner).copied().unwrap_or(0), *k))
            .expect("a job of the top priority");
        let j = queued.remove(k);
        *placed.entry(j.owner.clone()).or_default() += 1;
        out.push(j);
    }
    out
}

/// The workers a job wanting `want` (0: all free) gets from `free`, given the `usable` pool
/// (free or not): of the kind with the most free throughput among those with `want` free
/// workers, oldest registration first; failing that, of a kind whose whole pool is smaller
/// than `want` and free (`want` is capped at the pool's size). None when no kind has enough.
pub(crate) fn pick(free: &[WorkerRecord], usable: &[WorkerRecord], want: u32) -> Option<Vec<WorkerRecord>> {
    let mut kinds: BTreeMap<String, (f64, Vec<WorkerRecord>)> = BTreeMap::new();
    for w in free {
        let e = kinds.entry(w.kind()).or_default();
        e.0 += w.ad.atom_steps_per_s.max(0.0);
        e.1.push(w.clone());
    }
    let mut kinds: Vec<(String, (f64, Vec<WorkerRecord>))> = kinds.into_iter().collect();
    kinds.sort_by(|a, b| b.1.0.total_cmp(&a.1.0).then(a.0.cmp(&b.0)));
    for capped in [false, true] {
        for (kind, (_, ws)) in &kinds {
            let pool = usable.iter().filter(|w| &w.kind() == kind).count();
            let n = match (want, capped) {
                (0, _) => ws.len(),
                (n, false) => n as usize,
                (n, true) => (n as usize).min(pool),
            };
            if n > 0 && ws.len() >= n {
                return Some(ws.iter().take(n).cloned().collect());
            }
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::service::store::{WorkerAd, WorkerState, test_job};

    fn job(id: &str, owner: &str, priority: i32) -> JobRecord {
        let mut j = test_job(id, priority);
        j.owner = owner.into();
        j
    }

    fn ids(v: &[JobRecord]) -> Vec<&str> {
        v.iter().map(|j| j.id.as_str()).collect()
    }

    #[test]
    fn the_queue_goes_by_priority_then_fair_share_then_submission() {
        // As the store returns them: priority, then submission.
        let q = vec![job("h", "bob", 5), job("a1", "alice", 0), job("a2", "alice", 0), job("a3", "alice", 0), job("b1", "bob", 0)];
        // Bob's urgent job counts as his: among priority 0, Alice's first job goes first, then
        // they alternate (ties in submission order).
        assert_eq!(ids(&order(q.clone(), &HashMap::new())), vec!["h", "a1", "a2", "b1", "a3"]);
        assert_eq!(ids(&order(q[1..].to_vec(), &HashMap::new())), vec!["a1", "b1", "a2", "a3"]);
        // Alice has two running: Bob's job comes first among priority 0.
        let running = HashMap::from([("alice".to_string(), 2), ("bob".to_string(), 0)]);
        assert_eq!(ids(&order(q[1..].to_vec(), &running)), vec!["b1", "a1", "a2", "a3"]);
        assert!(order(Vec::new(), &running).is_empty());
    }

    fn w(epoch: u64, backend: &str, tp: f64) -> WorkerRecord {
        WorkerRecord {
            id: format!("w{epoch}"),
            epoch,
            ad: WorkerAd {
                address: format!("h:{epoch}"),
                backend: backend.into(),
                precision: "double".into(),
                atom_steps_per_s: tp,
                ..Default::default()
            },
            state: WorkerState::Live,
            registered: 0,
            note: String::new(),
        }
    }

    fn epochs(p: Option<Vec<WorkerRecord>>) -> Option<Vec<u64>> {
        p.map(|v| v.iter().map(|w| w.epoch).collect())
    }

    #[test]
    fn a_job_gets_its_number_of_free_workers_of_one_kind() {
        let usable = vec![w(1, "cpu", 1.0), w(2, "cpu", 1.0), w(3, "cpu", 1.0), w(4, "cuda", 5.0)];
        assert_eq!(epochs(pick(&usable, &usable, 1)), Some(vec![4]), "the kind with the most throughput");
        assert_eq!(epochs(pick(&usable, &usable, 2)), Some(vec![1, 2]), "the kind that has 2");
        assert_eq!(epochs(pick(&usable[3..], &usable, 2)), Some(vec![4]), "the cuda pool has 1: capped at 1");
        assert_eq!(epochs(pick(&usable[..3], &usable, 2)), Some(vec![1, 2]));
        assert_eq!(epochs(pick(&usable[..3], &usable, 0)), Some(vec![1, 2, 3]), "all");
        assert_eq!(epochs(pick(&usable[1..3], &usable, 3)), None, "3 of 3 cpu workers wanted, 2 free");
        assert_eq!(epochs(pick(&usable[1..3], &usable, 9)), None);
        assert_eq!(epochs(pick(&usable[..3], &usable, 9)), Some(vec![1, 2, 3]), "more than the pool: the pool");
        assert_eq!(epochs(pick(&[], &usable, 0)), None);
        // The cuda worker is busy: the cpu ones take a job wanting 2.
        assert_eq!(epochs(pick(&usable[..3], &usable, 2)), Some(vec![1, 2]));
    }
}
