//! What the service's domain core returns when a call cannot be done. It becomes a
//! `tonic::Status` only at the gRPC edge ([`super::api`]).

use super::store::JobState;
use super::workers::WorkerError;

#[derive(Debug, thiserror::Error)]
pub enum JobError {
    #[error("no job {0:?}")]
    NotFound(String),
    #[error("job {id} has already ended ({})", .state.as_str())]
    Ended { id: String, state: JobState },
    /// The submitted scene does not validate: the message `mscale check` prints.
    #[error(transparent)]
    BadScene(#[from] crate::scene::SceneError),
    #[error("file {name:?}: its content hashes to {actual}, not the SHA-256 {sent} it was sent with")]
    BadFile { name: String, actual: String, sent: String },
    #[error(
        "job {id} has events up to {newest}; after_sequence {after} is beyond them (is this the orchestrator, and state directory, the watch began with?)"
    )]
    BeyondEvents { id: String, newest: u64, after: u64 },
    #[error("{0:?} is not a path inside the job's run directory")]
    NotInRun(String),
    #[error("job {0} has no run directory yet")]
    NoRunDir(String),
    /// A file of the run directory that cannot be read.
    #[error("{path}")]
    Unreadable { path: String, source: std::io::Error },
    #[error("{path} has {len} bytes, more than one message carries ({limit})")]
    TooLarge { path: String, len: u64, limit: usize },
    #[error("{call} needs a bearer token (mscale: --token-file FILE or MSCALE_TOKEN)")]
    NoToken { call: String },
    #[error("{call}: the bearer token is not this orchestrator's")]
    WrongToken { call: String },
    /// The token is known, but its user or role may not make the call.
    #[error("{call}: user {user} (role {role}) may not make this call: {why}")]
    Forbidden { call: String, user: String, role: &'static str, why: &'static str },
    /// A per-user limit refuses the submission.
    #[error("user {user}: {what}")]
    Limit { user: String, what: String },
    #[error("the orchestrator is stopping; the job resumes when it restarts")]
    Stopping,
    /// A job's MPI ranks that this orchestrator cannot give it.
    #[error("{0}")]
    Ranks(String),
    #[error(transparent)]
    Worker(#[from] WorkerError),
    /// The job store, or a write under the state directory, failed.
    #[error(transparent)]
    Internal(#[from] anyhow::Error),
    /// A file of the state directory could not be written.
    #[error("{what}")]
    Io { what: String, source: std::io::Error },
    #[error("task failed")]
    Task(#[from] tokio::task::JoinError),
}

impl JobError {
    /// The message with every cause after it (`a: b: c`).
    pub fn chain(&self) -> String {
        let mut text = self.to_string();
        let mut cause = std::error::Error::source(self);
        while let Some(c) = cause {
            text.push_str(": ");
            text.push_str(&c.to_string());
            cause = c.source();
        }
        text
    }
}
