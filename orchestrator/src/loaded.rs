//! A scene of either kind, read once: an MPM scene (continuum bodies, optional MD) or a cell
//! scene (`kind = "cell"`, the PNP full cell). `mscale run`, `mscale check` and the job
//! service go through [`Loaded`], so every verb that takes a scene takes both kinds and the
//! choice is made in one place.

use crate::cell_run::{self, LoadedCell};
use crate::run::{self, Outcome, RunOptions};
use crate::scene::{self, LoadedScene, SceneError};
use anyhow::Result;
use std::path::{Path, PathBuf};

/// A read, overridden and validated scene.
#[derive(Debug, Clone)]
pub enum Loaded {
    Mpm(Box<LoadedScene>),
    Cell(Box<LoadedCell>),
}

impl Loaded {
    /// Reads a scene file with `--set` overrides; its `kind` picks the loader.
    pub fn load(path: &Path, sets: &[String]) -> Result<Loaded, SceneError> {
        if cell_run::is_cell_scene(path) {
            cell_run::load(path, sets).map(|c| Loaded::Cell(Box::new(c)))
        } else {
            scene::load(path, sets).map(|l| Loaded::Mpm(Box::new(l)))
        }
    }

    pub fn name(&self) -> &str {
        match self {
            Loaded::Mpm(l) => &l.scene.name,
            Loaded::Cell(c) => &c.scene.name,
        }
    }

    /// Steps of the run when known in advance (0 for a cell run, whose steps are adaptive).
    pub fn steps(&self) -> u64 {
        match self {
            Loaded::Mpm(l) => l.steps,
            Loaded::Cell(_) => 0,
        }
    }

    /// The scene's own checkpoint interval in steps (0: none).
    pub fn checkpoint_every_steps(&self) -> u64 {
        match self {
            Loaded::Mpm(l) => l.scene.output.checkpoint_every_steps,
            Loaded::Cell(_) => 0,
        }
    }

    /// Whether a run needs MD workers (a cell run never does).
    pub fn needs_md(&self) -> bool {
        match self {
            Loaded::Mpm(l) => l.scene.needs_md(),
            Loaded::Cell(_) => false,
        }
    }

    /// Snapshots the run writes (`output.snapshots`; a cell run's profiles at its output times)
    /// and the key that sets them.
    pub fn snapshots(&self) -> (u64, &'static str) {
        match self {
            Loaded::Mpm(l) => (l.scene.output.snapshots as u64, "output.snapshots"),
            Loaded::Cell(c) => (c.scene.output.times_s.len() as u64, "output.times_s"),
        }
    }

    /// `runs/<scene>-<UTC timestamp>`.
    pub fn default_out_dir(&self) -> PathBuf {
        run::default_out_dir_named(self.name())
    }

    /// Runs the scene into `opts.out`. A cell run needs no MD workers: `opts.workers` is
    /// ignored for it.
    pub fn run(&self, opts: &RunOptions) -> Result<Outcome> {
        match self {
            Loaded::Mpm(l) => run::run(l, opts),
            Loaded::Cell(c) => cell_run::run(c, opts),
        }
    }
}
