//! The job store's schema, one migration per version (`PRAGMA user_version`), applied in
//! order by [`super::Store::open`] (`rusqlite_migration`). A store from a newer build (a
//! higher version) is refused rather than guessed at.

/// The schema version [`Store::open`] brings a store to (`PRAGMA user_version`).
pub const SCHEMA_VERSION: usize = 4;

/// Version 1: the tables. Stores written before the schema was versioned are at version 0
/// with some or all of these tables (`events` came last); `IF NOT EXISTS` keeps what they hold.
pub(crate) const SCHEMA_1: &str = "
    CREATE TABLE IF NOT EXISTS jobs (
        seq INTEGER PRIMARY KEY AUTOINCREMENT,
        id TEXT NOT NULL UNIQUE,
        scene TEXT NOT NULL,
        state TEXT NOT NULL,
        priority INTEGER NOT NULL,
        overrides TEXT NOT NULL,
        checkpoint_every INTEGER NOT NULL,
        step INTEGER NOT NULL DEFAULT 0,
        steps INTEGER NOT NULL DEFAULT 0,
        sim_time REAL NOT NULL DEFAULT 0,
        error TEXT NOT NULL DEFAULT '',
        state_digest TEXT NOT NULL DEFAULT '',
        submitted INTEGER NOT NULL,
        started INTEGER NOT NULL DEFAULT 0,
        finished INTEGER NOT NULL DEFAULT 0,
        resumes INTEGER NOT NULL DEFAULT 0
    );
    CREATE TABLE IF NOT EXISTS history (
        job_id TEXT NOT NULL,
        at INTEGER NOT NULL,
        state TEXT NOT NULL,
        note TEXT NOT NULL
    );
    CREATE TABLE IF NOT EXISTS workers (
        epoch INTEGER PRIMARY KEY AUTOINCREMENT,
        address TEXT NOT NULL,
        device TEXT NOT NULL,
        backend TEXT NOT NULL,
        precision TEXT NOT NULL,
        cores INTEGER NOT NULL,
        memory_bytes INTEGER NOT NULL,
        atom_steps_per_s REAL NOT NULL,
        throughput_source TEXT NOT NULL,
        protocol_version INTEGER NOT NULL,
        state TEXT NOT NULL,
        registered INTEGER NOT NULL,
        note TEXT NOT NULL DEFAULT ''
    );
    CREATE TABLE IF NOT EXISTS events (
        job_id TEXT NOT NULL,
        seq INTEGER NOT NULL,
        kind TEXT NOT NULL,
        at INTEGER NOT NULL,
        state TEXT NOT NULL,
        step INTEGER NOT NULL,
        steps INTEGER NOT NULL,
        sim_time REAL NOT NULL,
        message TEXT NOT NULL,
        detail BLOB NOT NULL,
        PRIMARY KEY (job_id, seq)
    ) WITHOUT ROWID;
    CREATE TABLE IF NOT EXISTS worker_history (
        epoch INTEGER NOT NULL,
        at INTEGER NOT NULL,
        state TEXT NOT NULL,
        note TEXT NOT NULL
    );";

/// Version 2: every job has numbered events. A job stored before events were numbered gets
/// one state event (number 1) with its state, step and error as stored, so a watcher replays
/// it like any other; the job's next event is number 2.
const SCHEMA_2: &str = "
    INSERT INTO events (job_id, seq, kind, at, state, step, steps, sim_time, message, detail)
    SELECT id, 1, 'state', CASE WHEN finished > 0 THEN finished ELSE submitted END, state, step, steps, sim_time, error, X''
    FROM jobs WHERE id NOT IN (SELECT job_id FROM events);";

/// Version 3: a job belongs to the user who submitted it and asks for a number of workers (0:
/// every free one). Jobs stored before users existed belong to `admin`, the user of the
/// single-token mode, and ask for every worker (what they got).
const SCHEMA_3: &str = "
    ALTER TABLE jobs ADD COLUMN owner TEXT NOT NULL DEFAULT 'admin';
    ALTER TABLE jobs ADD COLUMN workers INTEGER NOT NULL DEFAULT 0;
    CREATE INDEX IF NOT EXISTS jobs_by_owner ON jobs (owner, state);";

/// Version 4: a job's continuum may run over MPI ranks. Jobs stored before run in the
/// orchestrator's process (1 rank), as they did.
const SCHEMA_4: &str = "
    ALTER TABLE jobs ADD COLUMN ranks INTEGER NOT NULL DEFAULT 1;";

pub(crate) fn migrations() -> rusqlite_migration::Migrations<'static> {
    use rusqlite_migration::M;
    rusqlite_migration::Migrations::new(vec![M::up(SCHEMA_1), M::up(SCHEMA_2), M::up(SCHEMA_3), M::up(SCHEMA_4)])
}
