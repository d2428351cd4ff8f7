//! Exit codes of `mscale`, and the one mapping from an error to its code.

/// The run (or the verb) completed.
pub const OK: i32 = 0;
/// A run that failed: instability, lost worker, cancelled; any failure that is not bad input.
pub const RUN_FAILED: i32 = 1;
/// Bad usage or bad input.
pub const BAD_INPUT: i32 = 2;

/// A call the orchestrator refused, or that failed on the way: its status, kept whole so that
/// [`code_of`] can tell bad input from other failures.
#[derive(Debug, thiserror::Error)]
#[error("{} ({:?})", .0.message(), .0.code())]
pub struct Refused(pub tonic::Status);

/// The message of an error and its chain of sources, joined by `: `; one function with the
/// continuum's, which carries a closure's failure across MPI ranks in the same words.
pub use continuum::closure::error_chain as message;

/// The exit code of a failed verb: [`BAD_INPUT`] when anything in the error's chain is bad
/// input (a scene that does not validate, a body that cannot be set up from its scene, a
/// request the job service refused as invalid), [`RUN_FAILED`] otherwise.
pub fn code_of(e: &anyhow::Error) -> i32 {
    use crate::setup::SetupError;
    let bad_input = e.chain().any(|cause| {
        cause.is::<crate::scene::SceneError>()
            || cause.downcast_ref::<SetupError>().is_some_and(|s| matches!(s, SetupError::EmptyBody(_) | SetupError::MdUnavailable(_)))
            || cause.downcast_ref::<Refused>().is_some_and(|r| r.0.code() == tonic::Code::InvalidArgument)
            // The MD engine refused a value of the scene (a box, a potential, a data file).
            || cause.downcast_ref::<md_worker::MdError>().is_some_and(|m| {
                matches!(m, md_worker::MdError::Invalid { .. } | md_worker::MdError::Parse { .. } | md_worker::MdError::Unsupported(_))
            })
    });
    if bad_input { BAD_INPUT } else { RUN_FAILED }
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::Context;

    #[test]
    fn bad_input_anywhere_in_the_chain_is_exit_code_2() {
        let refused = |code| anyhow::Error::from(Refused(tonic::Status::new(code, "m")));
        assert_eq!(code_of(&refused(tonic::Code::InvalidArgument)), BAD_INPUT);
        assert_eq!(code_of(&refused(tonic::Code::InvalidArgument).context("submit")), BAD_INPUT);
        assert_eq!(code_of(&refused(tonic::Code::Unauthenticated)), RUN_FAILED);
        assert_eq!(code_of(&refused(tonic::Code::NotFound)), RUN_FAILED);
        let scene = crate::scene::SceneError {
            file: "s.toml".into(),
            location: String::new(),
            key: "k".into(),
            value: String::new(),
            problem: "p".into(),
        };
        assert_eq!(code_of(&Err::<(), _>(scene).context("loading").unwrap_err()), BAD_INPUT);
        assert_eq!(code_of(&anyhow::Error::from(crate::setup::SetupError::EmptyBody("b".into()))), BAD_INPUT);
        assert_eq!(code_of(&anyhow::anyhow!("InvalidArgument")), RUN_FAILED, "no string matching");
        // An MD engine refusal under the closure and setup errors (as a run reports it).
        let md = |e: md_worker::MdError| {
            anyhow::Error::from(crate::setup::SetupError::Md {
                body: "bar".into(),
                source: continuum::closure::ClosureError::Engine { context: "opening boxes".into(), source: Box::new(e) },
            })
        };
        assert_eq!(code_of(&md(md_worker::MdError::Invalid { what: "box".into(), msg: "m".into() })), BAD_INPUT);
        assert_eq!(code_of(&md(md_worker::MdError::Diverged { point: 3, msg: "m".into() })), RUN_FAILED);
    }
}
