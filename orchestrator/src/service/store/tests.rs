use super::schema::{SCHEMA_1, SCHEMA_VERSION};
use super::*;

fn job(id: &str, priority: i32) -> JobRecord {
    test_job(id, priority)
}

#[test]
fn priority_order_restart_and_history() {
    let dir = tempfile::tempdir().unwrap();
    {
        let mut s = Store::open(dir.path()).unwrap();
        s.insert(&job("a", 0)).unwrap();
        s.insert(&job("b", 5)).unwrap();
        s.insert(&job("c", 5)).unwrap();
        assert_eq!(s.next_queued().unwrap().unwrap().id, "b");
        assert!(s.transition("b", JobState::Running, "", "").unwrap());
        assert_eq!(s.next_queued().unwrap().unwrap().id, "c");
        assert!(s.transition("a", JobState::Cancelled, "cancelled by a user", "").unwrap());
        assert!(!s.transition("a", JobState::Running, "", "").unwrap(), "a final state is final");
    }
    // Reopened as after a crash: the running job is queued again, with a resume counted.
    let mut s = Store::open(dir.path()).unwrap();
    assert_eq!(s.requeue_interrupted().unwrap(), vec!["b".to_string()]);
    let b = s.get("b").unwrap().unwrap();
    assert_eq!((b.state, b.resumes, b.overrides.clone()), (JobState::Queued, 1, vec!["a.b=1".to_string()]));
    assert_eq!(s.get("a").unwrap().unwrap().state, JobState::Cancelled);
    let states: Vec<String> = s.history("b").unwrap().into_iter().map(|h| h.1).collect();
    assert_eq!(states, vec!["queued", "running", "queued"]);
}

#[test]
fn events_are_numbered_without_gaps_across_a_restart_and_old_progress_is_pruned() {
    let dir = tempfile::tempdir().unwrap();
    {
        let mut s = Store::open(dir.path()).unwrap();
        s.set_progress_retention(300);
        s.insert(&job("a", 0)).unwrap();
        assert!(s.transition("a", JobState::Running, "started", "").unwrap());
        for k in 1..=600 {
            let kind = if k % 100 == 0 { EventKind::Checkpoint } else { EventKind::Progress };
            let e = s.progress_event("a", kind, k, 1000, k as f64, "", b"d").unwrap();
            assert_eq!((e.seq, e.step, e.state), (k + 2, k, JobState::Running));
        }
    }
    // Reopened as after a crash: the numbering goes on after the newest event.
    let mut s = Store::open(dir.path()).unwrap();
    s.requeue_interrupted().unwrap();
    assert_eq!(s.last_sequence("a").unwrap(), 603);
    let e = s.transition_event("a", JobState::Cancelled, "cancelled", "", b"x").unwrap().unwrap();
    assert_eq!((e.seq, e.state, e.detail.as_slice()), (604, JobState::Cancelled, &b"x"[..]));
    let all = s.events_after("a", 0, 10_000).unwrap();
    let seqs: Vec<u64> = all.iter().map(|e| e.seq).collect();
    // Pruned at seq 512: progress events up to 512 - 300 = 212 are gone, the others kept.
    assert_eq!(&seqs[..2], &[1, 2]);
    assert!(all.iter().filter(|e| e.seq <= 212).all(|e| e.kind != EventKind::Progress), "old progress kept");
    assert!(seqs.contains(&102) && seqs.contains(&202), "checkpoint events are never pruned: {:?}", &seqs[..5]);
    assert!(seqs.windows(2).filter(|w| w[0] >= 212).all(|w| w[1] == w[0] + 1), "recent events have a hole");
    assert_eq!(all.last().map(|e| (e.seq, e.kind)), Some((604, EventKind::State)));
    assert_eq!(s.events_after("a", 600, 2).unwrap().iter().map(|e| e.seq).collect::<Vec<_>>(), vec![601, 602]);
    assert_eq!(s.events_after("a", 604, 10).unwrap().len(), 0);
    let states: Vec<(JobState, String)> = all.iter().filter(|e| e.kind == EventKind::State).map(|e| (e.state, e.message.clone())).collect();
    assert_eq!(
        states.iter().map(|s| s.0).collect::<Vec<_>>(),
        vec![JobState::Queued, JobState::Running, JobState::Queued, JobState::Cancelled]
    );
}

/// A raw connection to the store file in `dir`, as an older orchestrator left it.
fn raw(dir: &Path) -> Connection {
    Connection::open(dir.join("jobs.sqlite")).unwrap()
}

fn user_version(dir: &Path) -> i64 {
    raw(dir).query_row("PRAGMA user_version", [], |r| r.get(0)).unwrap()
}

#[test]
fn a_store_of_the_unversioned_schema_opens_with_its_jobs_and_events() {
    let dir = tempfile::tempdir().unwrap();
    {
        // What `Store::open` made before the schema had versions: every table, version 0.
        let db = raw(dir.path());
        db.execute_batch(SCHEMA_1).unwrap();
        db.execute("INSERT INTO jobs (id, scene, state, priority, overrides, checkpoint_every, steps, submitted) VALUES ('a', 's', 'running', 3, '[\"k=1\"]', 10, 100, 5)", []).unwrap();
        db.execute("INSERT INTO events VALUES ('a', 1, 'state', 5, 'queued', 0, 100, 0.0, 'submitted', X'')", []).unwrap();
        db.execute("INSERT INTO events VALUES ('a', 2, 'state', 6, 'running', 0, 100, 0.0, 'started', X'')", []).unwrap();
        db.execute("INSERT INTO workers (address, device, backend, precision, cores, memory_bytes, atom_steps_per_s, throughput_source, protocol_version, state, registered) VALUES ('127.0.0.1:1', 'cpu', 'cpu', 'double', 2, 0, 1e6, 'measured', 1, 'live', 5)", []).unwrap();
    }
    assert_eq!(user_version(dir.path()), 0);
    let mut s = Store::open(dir.path()).unwrap();
    assert_eq!(user_version(dir.path()), SCHEMA_VERSION as i64);
    let a = s.get("a").unwrap().unwrap();
    assert_eq!((a.state, a.priority, a.overrides.clone(), a.checkpoint_every), (JobState::Running, 3, vec!["k=1".to_string()], 10));
    // A job from before users belongs to the single-token mode's admin and takes every worker.
    assert_eq!((a.owner.as_str(), a.workers), ("admin", 0));
    // Its events are kept as they were (none added), and the numbering goes on.
    assert_eq!(
        s.events_after("a", 0, 10).unwrap().iter().map(|e| (e.seq, e.message.clone())).collect::<Vec<_>>(),
        vec![(1, "submitted".to_string()), (2, "started".to_string())]
    );
    assert_eq!(s.requeue_interrupted().unwrap(), vec!["a".to_string()]);
    assert_eq!(s.last_sequence("a").unwrap(), 3);
    assert_eq!(
        s.workers().unwrap().iter().map(|w| (w.id.clone(), w.state)).collect::<Vec<_>>(),
        vec![("w1".to_string(), WorkerState::Live)]
    );
    drop(s);
    // Opening again changes nothing.
    let s = Store::open(dir.path()).unwrap();
    assert_eq!(s.last_sequence("a").unwrap(), 3);
}

#[test]
fn a_job_stored_before_events_were_numbered_gets_its_state_as_event_1() {
    let dir = tempfile::tempdir().unwrap();
    {
        // A store older than numbered events: jobs and history only.
        let db = raw(dir.path());
        db.execute_batch(&SCHEMA_1[..SCHEMA_1.find("CREATE TABLE IF NOT EXISTS workers").unwrap()]).unwrap();
        db.execute("INSERT INTO jobs (id, scene, state, priority, overrides, checkpoint_every, step, steps, submitted, finished, error) VALUES ('old', 's', 'failed', 0, '[]', 0, 40, 100, 5, 9, 'it broke')", []).unwrap();
    }
    let mut s = Store::open(dir.path()).unwrap();
    let ev = s.events_after("old", 0, 10).unwrap();
    assert_eq!(ev.len(), 1);
    assert_eq!(
        (ev[0].seq, ev[0].kind, ev[0].state, ev[0].step, ev[0].at, ev[0].message.as_str()),
        (1, EventKind::State, JobState::Failed, 40, 9, "it broke")
    );
    assert_eq!(s.note_event("old", EventKind::Workers, "later", &[]).unwrap().seq, 2);
}

#[test]
fn a_store_of_a_newer_schema_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    drop(Store::open(dir.path()).unwrap());
    raw(dir.path()).execute_batch(&format!("PRAGMA user_version = {}", SCHEMA_VERSION + 1)).unwrap();
    let e = Store::open(dir.path()).err().expect("a newer store opened");
    assert!(format!("{e:#}").contains("schema version"), "{e:#}");
}

#[test]
fn workers_get_a_new_epoch_per_registration_and_lost_is_final() {
    let dir = tempfile::tempdir().unwrap();
    let ad = |addr: &str| WorkerAd {
        address: addr.into(),
        backend: "cpu".into(),
        precision: "double".into(),
        atom_steps_per_s: 1e6,
        protocol_version: 1,
        ..Default::default()
    };
    let mut s = Store::open(dir.path()).unwrap();
    let (a, replaced) = s.register_worker(&ad("127.0.0.1:1")).unwrap();
    assert!(replaced.is_empty());
    let (b, _) = s.register_worker(&ad("127.0.0.1:2")).unwrap();
    assert!(b.epoch > a.epoch && a.id != b.id);
    assert!(s.set_worker_state(a.epoch, WorkerState::Draining, "drained by a user").unwrap());
    // The same address again: a new worker; the old registration is lost for good.
    let (c, replaced) = s.register_worker(&ad("127.0.0.1:1")).unwrap();
    assert_eq!(replaced, vec![a.id.clone()]);
    assert!(c.epoch > b.epoch);
    assert!(!s.set_worker_state(a.epoch, WorkerState::Live, "").unwrap(), "lost is final");
    drop(s);
    let s = Store::open(dir.path()).unwrap();
    let states: Vec<(String, WorkerState)> = s.workers().unwrap().into_iter().map(|w| (w.id, w.state)).collect();
    assert_eq!(states, vec![(a.id.clone(), WorkerState::Lost), (b.id, WorkerState::Live), (c.id, WorkerState::Live)]);
    let h: Vec<String> = s.worker_history(a.epoch).unwrap().into_iter().map(|h| h.1).collect();
    assert_eq!(h, vec!["live", "draining", "lost"]);
    // Many at once (a monitor pass): one transaction; the lost one and an unknown one stay out.
    let mut s = s;
    let moves = vec![(b.epoch, "silent".to_string()), (a.epoch, "x".to_string()), (999, "x".to_string()), (c.epoch, "silent".to_string())];
    assert_eq!(s.set_workers_state(&moves, WorkerState::Lost).unwrap(), vec![true, false, false, true]);
    assert!(s.workers().unwrap().iter().all(|w| w.state == WorkerState::Lost));
    assert_eq!(s.worker_history(c.epoch).unwrap().last().unwrap().1, "lost");
    assert_eq!(s.worker_history(a.epoch).unwrap().len(), 3);
}

#[test]
fn jobs_keep_their_owner_and_workers_and_are_listed_per_owner() {
    let dir = tempfile::tempdir().unwrap();
    let mut s = Store::open(dir.path()).unwrap();
    for (id, owner, workers, priority) in [("a", "alice", 2, 0), ("b", "bob", 0, 5), ("c", "alice", 1, 5)] {
        let mut j = test_job(id, priority);
        (j.owner, j.workers) = (owner.into(), workers);
        s.insert(&j).unwrap();
    }
    drop(s);
    let mut s = Store::open(dir.path()).unwrap();
    let a = s.get("a").unwrap().unwrap();
    assert_eq!((a.owner.as_str(), a.workers), ("alice", 2));
    let ids = |v: Vec<JobRecord>| v.into_iter().map(|j| j.id).collect::<Vec<_>>();
    assert_eq!(ids(s.list_of("alice").unwrap()), vec!["a", "c"]);
    assert_eq!(ids(s.list_of("carol").unwrap()), Vec::<String>::new());
    assert_eq!(ids(s.queued().unwrap()), vec!["b", "c", "a"]);
    assert_eq!(s.active_jobs("alice").unwrap(), 2);
    s.transition("a", JobState::Running, "started", "").unwrap();
    s.transition("c", JobState::Cancelled, "", "").unwrap();
    assert_eq!(s.active_jobs("alice").unwrap(), 1);
    assert_eq!(s.active_jobs("bob").unwrap(), 1);
}
