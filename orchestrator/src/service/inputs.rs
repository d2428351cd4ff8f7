//! Submitted jobs: their scene and the files it names, written under `jobs/<id>/input/` and
//! validated with the messages of `mscale check`.

use super::auth::{Caller, constant_time_eq};
use super::error::JobError;
use super::shared::{Core, lock};
use super::store::{JobRecord, JobState, now_unix};
use crate::loaded::Loaded;
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::Path;

/// A job as submitted.
pub(crate) struct Submission {
    pub(crate) scene_text: String,
    pub(crate) files: Vec<InputFile>,
    /// `--set` overrides, in order.
    pub(crate) overrides: Vec<String>,
    pub(crate) priority: i32,
    /// Steps (0: the orchestrator's default).
    pub(crate) checkpoint_every: u64,
    /// The scene's file name on the submitting side, for messages.
    pub(crate) scene_file: String,
    /// Workers wanted (0: every free one).
    pub(crate) workers: u32,
    /// MPI ranks of its continuum (0 or 1: in the orchestrator's process).
    pub(crate) ranks: u32,
}

/// A file a submitted scene names.
pub(crate) struct InputFile {
    /// As the scene names it.
    pub(crate) name: String,
    pub(crate) sha256: String,
    pub(crate) content: Vec<u8>,
}

/// Applies `f` to every string value of a TOML document.
pub fn for_each_string(item: &mut toml_edit::Item, f: &mut dyn FnMut(&mut toml_edit::Value)) {
    fn value(v: &mut toml_edit::Value, f: &mut dyn FnMut(&mut toml_edit::Value)) {
        match v {
            toml_edit::Value::String(_) => f(v),
            toml_edit::Value::Array(a) => a.iter_mut().for_each(|v| value(v, f)),
            toml_edit::Value::InlineTable(t) => t.iter_mut().for_each(|(_, v)| value(v, f)),
            _ => {}
        }
    }
    match item {
        toml_edit::Item::Value(v) => value(v, f),
        toml_edit::Item::Table(t) => t.iter_mut().for_each(|(_, i)| for_each_string(i, f)),
        toml_edit::Item::ArrayOfTables(a) => a.iter_mut().for_each(|t| t.iter_mut().for_each(|(_, i)| for_each_string(i, f))),
        toml_edit::Item::None => {}
    }
}

/// A stored input file's name: a prefix of its hash and its base name, nothing else.
fn stored_name(f: &InputFile) -> String {
    let base = Path::new(&f.name).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let base: String = base.chars().map(|c| if c.is_ascii_alphanumeric() || "._-".contains(c) { c } else { '_' }).collect();
    format!("{}-{base}", &f.sha256[..16.min(f.sha256.len())])
}

/// Writes a submitted job's inputs into `dir/input` (files checked against their SHA-256, the
/// scene's references to them rewritten) and validates the scene: the error text is the one
/// `mscale check` prints.
fn prepare_inputs(dir: &Path, sub: &Submission) -> Result<Loaded, JobError> {
    let input = dir.join("input");
    std::fs::create_dir_all(input.join("files"))
        .map_err(|source| JobError::Io { what: format!("cannot create {}", input.display()), source })?;
    let mut renames = HashMap::new();
    for f in &sub.files {
        let actual = hex::encode(Sha256::digest(&f.content));
        if !constant_time_eq(actual.as_bytes(), f.sha256.to_ascii_lowercase().as_bytes()) {
            return Err(JobError::BadFile { name: f.name.clone(), actual, sent: f.sha256.clone() });
        }
        let name = format!("files/{}", stored_name(f));
        crate::atomic::write(&input.join(&name), &f.content)?;
        renames.insert(f.name.clone(), name);
    }
    let mut doc: toml_edit::DocumentMut = match sub.scene_text.parse() {
        Ok(d) => d,
        // Not TOML: store it as is, so the scene loader reports it with its own message.
        Err(_) => toml_edit::DocumentMut::new(),
    };
    let text = if doc.is_empty() && !sub.scene_text.trim().is_empty() {
        sub.scene_text.clone()
    } else {
        for_each_string(doc.as_item_mut(), &mut |v| {
            if let Some(new) = v.as_str().and_then(|s| renames.get(s)) {
                let decor = v.decor().clone();
                *v = toml_edit::Value::from(new.as_str());
                *v.decor_mut() = decor;
            }
        });
        doc.to_string()
    };
    let scene_path = input.join("scene.toml");
    crate::atomic::write(&scene_path, text.as_bytes())?;
    Loaded::load(&scene_path, &sub.overrides).map_err(|mut e| {
        if !sub.scene_file.is_empty() {
            e.file = sub.scene_file.clone();
        }
        JobError::BadScene(e)
    })
}

impl Core {
    /// Queues a job submitted by `caller` (within its limits, its inputs written and its
    /// scene valid); returns its id.
    pub(crate) fn submit(&self, caller: &Caller, sub: &Submission) -> Result<String, JobError> {
        let limits = caller.limits;
        let limit = |what: String| JobError::Limit { user: caller.user.clone(), what };
        let uploaded: u64 = sub.scene_text.len() as u64 + sub.files.iter().map(|f| f.content.len() as u64).sum::<u64>();
        if let Some(max) = limits.max_upload_bytes.filter(|m| uploaded > *m) {
            return Err(limit(format!(
                "the job uploads {uploaded} bytes (the scene and the files it names), over the limit max_upload_bytes = {max}"
            )));
        }
        if let Some(max) = limits.max_jobs {
            let active = lock(&self.store).active_jobs(&caller.user)?;
            if active >= max {
                return Err(limit(format!(
                    "{active} jobs are queued or running, the limit max_jobs = {max}; wait for one to end or cancel one"
                )));
            }
        }
        let ranks = sub.ranks.max(1);
        if ranks > 1 && self.mpi.is_none() {
            return Err(JobError::Ranks(format!(
                "the job asks for {ranks} MPI ranks, but this orchestrator runs jobs in its own process only: start it with `mscale serve --mpi-mscale PATH` (an mscale built with --features mpi), or submit with --ranks 1"
            )));
        }
        let id = self.new_id();
        let dir = self.job_dir(&id);
        let loaded = prepare_inputs(&dir, sub).inspect_err(|_| {
            let _ = std::fs::remove_dir_all(&dir);
        })?;
        if ranks > 1 && matches!(loaded, Loaded::Cell(_)) {
            let _ = std::fs::remove_dir_all(&dir);
            return Err(JobError::Ranks(format!(
                "the job asks for {ranks} MPI ranks, but a cell scene ({}) runs in one process only: submit it with --ranks 1",
                loaded.name()
            )));
        }
        let (snapshots, key) = loaded.snapshots();
        if let Some(max) = limits.max_snapshots.filter(|m| snapshots > *m) {
            let _ = std::fs::remove_dir_all(&dir);
            return Err(limit(format!(
                "the scene writes {key} = {snapshots} snapshots, over the limit max_snapshots = {max}; write fewer (--set {key}=...)"
            )));
        }
        let job = JobRecord {
            id: id.clone(),
            scene: loaded.name().to_string(),
            state: JobState::Queued,
            priority: sub.priority,
            overrides: sub.overrides.clone(),
            checkpoint_every: sub.checkpoint_every,
            step: 0,
            steps: loaded.steps(),
            sim_time: 0.0,
            error: String::new(),
            state_digest: String::new(),
            submitted: now_unix(),
            started: 0,
            finished: 0,
            resumes: 0,
            owner: caller.user.clone(),
            workers: sub.workers,
            ranks,
        };
        {
            // Checked again with the insert: two submits at once do not both pass the limit.
            let mut store = lock(&self.store);
            if let Some(max) = limits.max_jobs {
                let active = store.active_jobs(&caller.user)?;
                if active >= max {
                    drop(store);
                    let _ = std::fs::remove_dir_all(&dir);
                    return Err(limit(format!(
                        "{active} jobs are queued or running, the limit max_jobs = {max}; wait for one to end or cancel one"
                    )));
                }
            }
            store.insert(&job)?;
        }
        let mut wants = if job.workers == 0 { "every free worker".to_string() } else { format!("{} workers", job.workers) };
        if job.ranks > 1 {
            wants.push_str(&format!(", {} MPI ranks", job.ranks));
        }
        tracing::info!("job {id} queued for {}: scene {} ({} steps), priority {}, {wants}", job.owner, job.scene, job.steps, job.priority);
        self.wake_runner();
        Ok(id)
    }
}
