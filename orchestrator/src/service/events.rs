//! Job events as watchers get them. Every event of a job has a sequence number (1, 2, 3, ...
//! with no gaps), given in the store transaction that records it. Watchers replay what they
//! missed from the store and then follow a broadcast channel; one that lags is caught up from
//! the store again, so an event is never skipped.

use super::convert::{event_of, is_final, not_retained};
use super::error::JobError;
use super::shared::{Core, lock};
use super::store::{EventKind, JobState};
use mscale_proto::orchestrator::v1 as pb;
use std::sync::Arc;
use tokio::sync::{broadcast, mpsc, watch};

/// Events a watcher may fall behind by before it is caught up from the store.
pub(crate) const WATCH_BACKLOG: usize = 256;
/// Events read from the store at a time when a watcher catches up.
const REPLAY_BATCH: usize = 512;

/// The broadcast of a watched job's events.
pub(crate) struct LiveJob {
    pub(crate) tx: broadcast::Sender<Arc<pb::JobEvent>>,
    /// The newest sequence number sent on `tx`.
    published: u64,
}

/// What a watch stream carries.
pub(crate) type EventSender = mpsc::Sender<Result<pb::JobEvent, JobError>>;

impl Core {
    /// Subscribes to a job's events; returns the receiver and the newest sequence number at
    /// that moment (every later event comes through the receiver or, if it lags, the store).
    pub(crate) fn subscribe(&self, id: &str) -> Result<(broadcast::Receiver<Arc<pb::JobEvent>>, u64), JobError> {
        let store = lock(&self.store);
        let last = store.last_sequence(id)?;
        let mut live = lock(&self.live);
        let job = live.entry(id.to_string()).or_insert_with(|| LiveJob { tx: broadcast::channel(WATCH_BACKLOG).0, published: last });
        Ok((job.tx.subscribe(), last))
    }

    /// Drops a job's channel when its last watcher has gone.
    pub(crate) fn unsubscribe(&self, id: &str) {
        let mut live = lock(&self.live);
        if live.get(id).is_some_and(|j| j.tx.receiver_count() == 0) {
            live.remove(id);
        }
    }

    /// Sends the job's stored events its watchers have not been sent yet (after every change
    /// the store records); in sequence order, as the store lock is held throughout.
    pub(crate) fn publish_stored(&self, id: &str) {
        let store = lock(&self.store);
        let mut live = lock(&self.live);
        let Some(job) = live.get_mut(id) else { return }; // nobody watches: watchers read the store
        loop {
            let events = match store.events_after(id, job.published, REPLAY_BATCH) {
                Ok(e) => e,
                Err(e) => {
                    tracing::error!("job {id}: cannot read its events: {e:#}");
                    return;
                }
            };
            for e in &events {
                job.published = e.seq;
                // No receiver: the watcher is gone or about to subscribe (it reads the store).
                let _ = job.tx.send(Arc::new(event_of(e)));
            }
            if events.len() < REPLAY_BATCH {
                return;
            }
        }
    }

    /// Records a job's note (a worker change, a checkpoint) as an event and publishes it.
    pub(crate) fn note_event(&self, id: &str, kind: EventKind, text: &str) {
        let detail = lock(&self.details).get(id).cloned().unwrap_or_default();
        let noted = lock(&self.store).note_event(id, kind, text, &detail);
        if let Err(e) = noted {
            tracing::error!("job {id}: cannot record {text:?}: {e:#}");
        }
        self.publish_stored(id);
    }

    /// Records a worker change of a job.
    pub(crate) fn note(&self, id: &str, text: &str) {
        self.note_event(id, EventKind::Workers, text);
    }

    /// Moves a job to `state`, recorded with its event, and publishes it.
    pub(crate) fn transition(&self, id: &str, state: JobState, note: &str, digest: &str) {
        let detail = if state.is_final() { lock(&self.details).remove(id) } else { lock(&self.details).get(id).cloned() };
        let moved = lock(&self.store).transition_event(id, state, note, digest, &detail.unwrap_or_default());
        if let Err(e) = moved {
            tracing::error!("job {id}: cannot record {}: {e:#}", state.as_str());
        }
        self.publish_stored(id);
    }

    /// The events of a job after `after`, in order and each once, until its final one; the
    /// stream ends early (with an error) when the orchestrator stops.
    pub(crate) fn watch(self: &Arc<Self>, id: &str, after: u64) -> Result<mpsc::Receiver<Result<pb::JobEvent, JobError>>, JobError> {
        self.get(id)?;
        let (rx, newest) = self.subscribe(id)?;
        if after > newest {
            drop(rx);
            self.unsubscribe(id);
            return Err(JobError::BeyondEvents { id: id.to_string(), newest, after });
        }
        let (tx, out) = mpsc::channel(16);
        let (core, mut stop, id) = (self.clone(), self.stop_watchers.subscribe(), id.to_string());
        tokio::spawn(async move {
            follow(&core, &id, after + 1, rx, &mut stop, &tx).await;
            core.unsubscribe(&id);
        });
        Ok(out)
    }
}

/// Sends a watcher the job's events from `next` on, in order and each once, until the final one:
/// first from the store, then from the job's channel; whenever the channel lags or shows a
/// gap, from the store again.
async fn follow(
    core: &Arc<Core>,
    id: &str,
    mut next: u64,
    mut rx: broadcast::Receiver<Arc<pb::JobEvent>>,
    stop: &mut watch::Receiver<bool>,
    tx: &EventSender,
) {
    let mut catch_up = true;
    loop {
        if catch_up {
            match replay(core, id, &mut next, tx).await {
                Ok(true) => return,
                Ok(false) => catch_up = false,
                Err(e) => {
                    let _ = tx.send(Err(e)).await;
                    return;
                }
            }
        }
        if *stop.borrow() {
            let _ = tx.send(Err(JobError::Stopping)).await;
            return;
        }
        tokio::select! {
            r = rx.recv() => match r {
                Ok(ev) if ev.sequence < next => {}
                Ok(ev) if ev.sequence == next => {
                    next += 1;
                    let last = is_final(ev.state);
                    if tx.send(Ok((*ev).clone())).await.is_err() || last {
                        return;
                    }
                }
                // Ahead of what this watcher has (it lagged, or the event was stored by a
                // path that does not publish): the store has the ones in between.
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => catch_up = true,
                Err(broadcast::error::RecvError::Closed) => {
                    let _ = replay(core, id, &mut next, tx).await;
                    return;
                }
            },
            _ = stop.changed() => {}
        }
    }
}

/// Sends the stored events from `next` on (a hole left by pruned progress events as one
/// JOB_EVENT_KIND_NOT_RETAINED event); true when the stream is over (the final event was sent,
/// or the watcher has gone).
async fn replay(core: &Arc<Core>, id: &str, next: &mut u64, tx: &EventSender) -> Result<bool, JobError> {
    loop {
        let (c, job, after) = (core.clone(), id.to_string(), *next - 1);
        let events = tokio::task::spawn_blocking(move || {
            lock(&c.store).events_after(&job, after, REPLAY_BATCH).map_err(|e| e.context(format!("job {job}: cannot read its events")))
        })
        .await??;
        for e in &events {
            if e.seq > *next && tx.send(Ok(not_retained(id, *next, e.seq - 1))).await.is_err() {
                return Ok(true);
            }
            *next = e.seq + 1;
            if tx.send(Ok(event_of(e))).await.is_err() || e.state.is_final() {
                return Ok(true);
            }
        }
        if events.len() < REPLAY_BATCH {
            return Ok(false);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::store::test_job;
    use super::*;

    #[test]
    fn a_watcher_that_falls_behind_is_caught_up_from_the_store() {
        let dir = tempfile::tempdir().unwrap();
        let core = Core::for_test(dir.path());
        lock(&core.store).insert(&test_job("j1", 0)).unwrap();
        let published = WATCH_BACKLOG as u64 + 50;
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        rt.block_on(async {
            let (rx, newest) = core.subscribe("j1").unwrap();
            assert_eq!(newest, 1);
            let (tx, mut out) = mpsc::channel(100_000);
            let (c, mut stop) = (core.clone(), core.stop_watchers.subscribe());
            let watcher = tokio::spawn(async move { follow(&c, "j1", 1, rx, &mut stop, &tx).await });
            // The stored event comes first (replayed); then the watcher waits on the channel.
            assert_eq!(out.recv().await.unwrap().unwrap().sequence, 1);
            // More events than the channel holds, published while the watcher cannot run (one
            // thread, no await): its receiver lags and loses the oldest.
            core.transition("j1", JobState::Running, "started", "");
            for k in 1..=published {
                lock(&core.store).progress_event("j1", EventKind::Progress, k, 1000, 0.0, "", &[]).unwrap();
                core.publish_stored("j1");
            }
            core.transition("j1", JobState::Completed, "", "digest");
            let mut seqs = vec![1];
            while let Some(ev) = out.recv().await {
                let ev = ev.unwrap();
                seqs.push(ev.sequence);
                if is_final(ev.state) {
                    break;
                }
            }
            assert_eq!(seqs, (1..=published + 3).collect::<Vec<_>>(), "the watcher skipped events");
            watcher.await.unwrap();
        });
        // The watcher has gone: its channel too.
        assert!(lock(&core.live).get("j1").is_some_and(|j| j.tx.receiver_count() == 0));
        core.unsubscribe("j1");
        assert!(lock(&core.live).is_empty());
    }
}
