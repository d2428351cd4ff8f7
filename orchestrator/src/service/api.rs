//! The gRPC edge of the service: decodes a call, runs it on the domain core ([`Core`]), encodes
//! the answer, and turns a [`JobError`] into a `tonic::Status` (here only).

use super::auth::{Caller, Need};
use super::convert::{job_to_pb, worker_to_pb};
use super::error::JobError;
use super::fetch::{FETCH_CHUNK, send_run};
use super::shared::{Core, lock};
use super::store::WorkerAd;
use super::workers::WorkerError;
use mscale_proto::orchestrator::v1 as pb;
use pb::orchestrator_server::Orchestrator;
use std::pin::Pin;
use std::sync::Arc;
use tokio_stream::{Stream, StreamExt};
use tonic::{Code, Request, Response, Status};

impl From<JobError> for Status {
    fn from(e: JobError) -> Status {
        let code = match &e {
            JobError::NotFound(_) | JobError::NoRunDir(_) | JobError::Unreadable { .. } => Code::NotFound,
            JobError::Ended { .. } => Code::FailedPrecondition,
            JobError::BadScene(_) | JobError::BadFile { .. } | JobError::NotInRun(_) | JobError::Ranks(_) => Code::InvalidArgument,
            JobError::BeyondEvents { .. } => Code::OutOfRange,
            JobError::TooLarge { .. } => Code::ResourceExhausted,
            JobError::NoToken { .. } | JobError::WrongToken { .. } => Code::Unauthenticated,
            JobError::Forbidden { .. } => Code::PermissionDenied,
            JobError::Limit { .. } => Code::ResourceExhausted,
            JobError::Stopping => Code::Unavailable,
            JobError::Worker(WorkerError::Version { .. }) => Code::FailedPrecondition,
            JobError::Worker(WorkerError::Invalid(_)) => Code::InvalidArgument,
            JobError::Worker(WorkerError::NotFound(_)) => Code::NotFound,
            JobError::Worker(WorkerError::Store(_)) | JobError::Internal(_) | JobError::Io { .. } | JobError::Task(_) => Code::Internal,
        };
        Status::new(code, e.chain())
    }
}

/// The service: decodes, calls the core, encodes.
pub struct JobService {
    core: Arc<Core>,
}

impl JobService {
    pub(crate) fn new(core: Arc<Core>) -> Self {
        JobService { core }
    }

    /// Who makes a call (its bearer token), if they may.
    fn authorize<T>(&self, req: &Request<T>, call: &str, need: Need) -> Result<Caller, JobError> {
        let given = req.metadata().get("authorization").and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer ")).unwrap_or("");
        self.core.authorize(given.trim(), call, need)
    }

    /// Runs `f` on the blocking pool once `caller` is found to own job `id` (`Core::owned`).
    async fn on_owned<T: Send + 'static>(
        &self,
        caller: Caller,
        id: String,
        f: impl FnOnce(&Arc<Core>, &str) -> Result<T, JobError> + Send + 'static,
    ) -> Result<T, JobError> {
        let core = self.core.clone();
        blocking(move || {
            core.owned(&caller, &id)?;
            f(&core, &id)
        })
        .await
    }
}

/// Runs `f` on the blocking pool: every call that takes the store's or the registry's lock or
/// touches files goes through here, so a write to disk that stalls (the store syncs each
/// transaction) holds up the calls waiting for it, never the runtime's two threads and with
/// them every other call (workers' heartbeats included).
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> Result<T, JobError> + Send + 'static) -> Result<T, JobError> {
    tokio::task::spawn_blocking(f).await?
}

/// A watch stream's item as sent (tonic's stream items carry a `Status`).
#[allow(clippy::result_large_err)]
fn event_or_status(r: Result<pb::JobEvent, JobError>) -> Result<pb::JobEvent, Status> {
    r.map_err(Status::from)
}

type EventStream = Pin<Box<dyn Stream<Item = Result<pb::JobEvent, Status>> + Send>>;
type ChunkStream = Pin<Box<dyn Stream<Item = Result<pb::FetchRunChunk, Status>> + Send>>;

#[tonic::async_trait]
impl Orchestrator for JobService {
    async fn submit_job(&self, req: Request<pb::SubmitJobRequest>) -> Result<Response<pb::SubmitJobResponse>, Status> {
        let caller = self.authorize(&req, "SubmitJob", Need::Jobs)?;
        let sub = req.into_inner().into();
        let core = self.core.clone();
        let job_id = blocking(move || core.submit(&caller, &sub)).await?;
        Ok(Response::new(pb::SubmitJobResponse { job_id }))
    }

    async fn list_jobs(&self, req: Request<pb::ListJobsRequest>) -> Result<Response<pb::ListJobsResponse>, Status> {
        let caller = self.authorize(&req, "ListJobs", Need::Read)?;
        let core = self.core.clone();
        let jobs = blocking(move || core.jobs_of(&caller)).await?;
        Ok(Response::new(pb::ListJobsResponse { jobs: jobs.iter().map(job_to_pb).collect() }))
    }

    async fn get_job(&self, req: Request<pb::GetJobRequest>) -> Result<Response<pb::Job>, Status> {
        let caller = self.authorize(&req, "GetJob", Need::Read)?;
        let (core, id) = (self.core.clone(), req.into_inner().job_id);
        Ok(Response::new(job_to_pb(&blocking(move || core.owned(&caller, &id)).await?)))
    }

    type WatchJobStream = EventStream;

    async fn watch_job(&self, req: Request<pb::WatchJobRequest>) -> Result<Response<EventStream>, Status> {
        let caller = self.authorize(&req, "WatchJob", Need::Read)?;
        let pb::WatchJobRequest { job_id, after_sequence } = req.into_inner();
        let events = self.on_owned(caller, job_id, move |core, id| core.watch(id, after_sequence)).await?;
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(events).map(event_or_status))))
    }

    async fn cancel_job(&self, req: Request<pb::CancelJobRequest>) -> Result<Response<pb::Job>, Status> {
        let caller = self.authorize(&req, "CancelJob", Need::Jobs)?;
        let id = req.into_inner().job_id;
        let job = self.on_owned(caller, id, |core, id| core.cancel(id)).await?;
        Ok(Response::new(job_to_pb(&job)))
    }

    async fn fetch_result(&self, req: Request<pb::FetchResultRequest>) -> Result<Response<pb::FetchResultResponse>, Status> {
        let caller = self.authorize(&req, "FetchResult", Need::Read)?;
        let req = req.into_inner();
        let (content, sha256) = self.on_owned(caller, req.job_id, move |core, id| core.fetch_result(id, &req.path)).await?;
        Ok(Response::new(pb::FetchResultResponse { content, sha256 }))
    }

    type FetchRunStream = ChunkStream;

    async fn fetch_run(&self, req: Request<pb::FetchRunRequest>) -> Result<Response<ChunkStream>, Status> {
        let caller = self.authorize(&req, "FetchRun", Need::Read)?;
        let req = req.into_inner();
        let root = self.on_owned(caller, req.job_id, |core, id| core.run_root(id)).await?;
        let chunk = if req.chunk_bytes == 0 { FETCH_CHUNK } else { (req.chunk_bytes as usize).min(FETCH_CHUNK) };
        let (tx, out) = tokio::sync::mpsc::channel(4);
        tokio::task::spawn_blocking(move || {
            if let Err(e) = send_run(&root, chunk, |c| tx.blocking_send(Ok(c.into())).is_ok()) {
                let _ = tx.blocking_send(Err(e.into()));
            }
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(out))))
    }

    async fn register_worker(&self, req: Request<pb::RegisterWorkerRequest>) -> Result<Response<pb::RegisterWorkerResponse>, Status> {
        self.authorize(&req, "RegisterWorker", Need::Worker)?;
        let ad = WorkerAd::from(req.into_inner());
        let core = self.core.clone();
        let (w, timeout) = blocking(move || core.register_worker(ad)).await?;
        Ok(Response::new(pb::RegisterWorkerResponse { worker_id: w.id, epoch: w.epoch, timeout_s: timeout.as_secs_f64() }))
    }

    async fn heartbeat(&self, req: Request<pb::HeartbeatRequest>) -> Result<Response<pb::HeartbeatResponse>, Status> {
        self.authorize(&req, "Heartbeat", Need::Worker)?;
        let r = req.into_inner();
        let core = self.core.clone();
        // Off the runtime's threads: the registry's lock may be held over a write to disk.
        let drain =
            blocking(move || lock(&core.workers).heartbeat(&r.worker_id, r.epoch, r.protocol_version).map_err(JobError::from)).await?;
        Ok(Response::new(pb::HeartbeatResponse { drain }))
    }

    async fn drain_worker(&self, req: Request<pb::DrainWorkerRequest>) -> Result<Response<pb::Worker>, Status> {
        self.authorize(&req, "DrainWorker", Need::Admin)?;
        let id = req.into_inner().worker_id;
        let core = self.core.clone();
        let view = blocking(move || core.drain_worker(&id)).await?;
        Ok(Response::new(worker_to_pb(&view)))
    }

    async fn list_workers(&self, req: Request<pb::ListWorkersRequest>) -> Result<Response<pb::ListWorkersResponse>, Status> {
        self.authorize(&req, "ListWorkers", Need::Read)?;
        let core = self.core.clone();
        let workers = blocking(move || Ok(lock(&core.workers).list().iter().map(worker_to_pb).collect())).await?;
        Ok(Response::new(pb::ListWorkersResponse { workers }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_become_statuses_with_their_whole_message() {
        let s = Status::from(JobError::NotFound("j1".into()));
        assert_eq!((s.code(), s.message()), (Code::NotFound, "no job \"j1\""));
        let scene = crate::scene::SceneError {
            file: "s.toml".into(),
            location: "line 3".into(),
            key: "scheme.cfl".into(),
            value: "3".into(),
            problem: "must be at most 1".into(),
        };
        let text = scene.to_string();
        let s = Status::from(JobError::BadScene(scene));
        assert_eq!((s.code(), s.message()), (Code::InvalidArgument, text.as_str()));
        let s = Status::from(JobError::from(anyhow::anyhow!("disk full").context("cannot record the job")));
        assert_eq!((s.code(), s.message()), (Code::Internal, "cannot record the job: disk full"));
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "gone");
        let s = Status::from(JobError::Unreadable { path: "summary.json".into(), source: io });
        assert_eq!((s.code(), s.message()), (Code::NotFound, "summary.json: gone"));
        let s = Status::from(JobError::Worker(WorkerError::Version { theirs: 2, ours: 1 }));
        assert_eq!(s.code(), Code::FailedPrecondition);
    }

    #[test]
    fn calls_waiting_for_a_held_lock_do_not_hold_up_the_others() {
        // The registry's lock held for a while (as over a stalled write to disk): heartbeats and
        // worker lists wait for it, on the blocking pool; a job's lookup on the runtime's only
        // thread still answers at once (it waited behind them when they locked on that thread).
        use super::super::store::test_job;
        use std::time::{Duration, Instant};
        let dir = tempfile::tempdir().unwrap();
        let core = Core::for_test(dir.path());
        lock(&core.store).insert(&test_job("j1", 0)).unwrap();
        let service = JobService::new(core.clone());
        fn req<T>(m: T) -> Request<T> {
            let mut r = Request::new(m);
            r.metadata_mut().insert("authorization", "Bearer t".parse().unwrap());
            r
        }
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let (held_tx, held_rx) = std::sync::mpsc::channel();
        let holder = std::thread::spawn({
            let core = core.clone();
            move || {
                let _reg = lock(&core.workers);
                held_tx.send(()).unwrap();
                std::thread::sleep(Duration::from_millis(1500));
            }
        });
        held_rx.recv().unwrap();
        let t0 = Instant::now();
        let (waited, got) = rt.block_on(async {
            let beat = || req(pb::HeartbeatRequest { worker_id: "w1".into(), epoch: 1, protocol_version: 1 });
            let lookup = async {
                let job = service.get_job(req(pb::GetJobRequest { job_id: "j1".into() })).await.unwrap().into_inner();
                (t0.elapsed(), job.id)
            };
            let (_, _, got) = tokio::join!(service.heartbeat(beat()), service.heartbeat(beat()), lookup);
            got
        });
        holder.join().unwrap();
        assert_eq!(got, "j1");
        assert!(waited < Duration::from_millis(1000), "GetJob waited {waited:?} behind calls waiting for the registry");
    }
}
