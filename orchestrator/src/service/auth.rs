//! Who calls: bearer tokens name users, each with a role (admin, user or worker), checked in
//! constant time on every call.
//!
//! Two modes. With one token (`mscale serve --token-file`, or the one generated into the
//! state directory) the token is the admin user `admin`, and read-only calls also work without
//! a token (as before users existed). With a users file (`mscale serve --users FILE`) every
//! call needs the token of a user in it; the file is read again on SIGHUP (a broken file is
//! reported and the users in force are kept). The file is TOML, one `[[user]]` table per
//! user:
//!
//! ```toml
//! [[user]]
//! name = "alice"
//! role = "user"            # admin, user or worker
//! token_sha256 = "<64 hex digits: SHA-256 of the token, e.g. printf %s TOKEN | sha256sum>"
//! max_jobs = 4             # optional limits, over the server's --max-jobs-per-user ...
//! max_upload_bytes = 1000000
//! max_snapshots = 20
//! ```
//!
//! Only hashes are stored; a token is found by hashing it and comparing the hash with every
//! user's, each in constant time (`subtle`), without stopping at the first match. Tokens are
//! meant to be long random strings (256 bits, like the generated one), for which SHA-256 is
//! enough: no slow password hash is needed.

use super::error::JobError;
use super::shared::Core;
use anyhow::{Context, Result, bail};
use serde::Deserialize;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};

/// Compares two byte strings in time that depends only on their lengths (`subtle`).
pub(crate) fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    use subtle::ConstantTimeEq;
    a.ct_eq(b).into()
}

/// Reads a token file (surrounding whitespace ignored); refuses an empty one.
pub fn read_token(path: &Path) -> Result<String> {
    let t = std::fs::read_to_string(path).with_context(|| format!("cannot read the token file {}", path.display()))?;
    let t = t.trim().to_string();
    anyhow::ensure!(!t.is_empty(), "the token file {} is empty", path.display());
    Ok(t)
}

/// A fresh token: 256 bits from the operating system, in hex.
pub(crate) fn random_token() -> Result<String> {
    let mut bytes = [0u8; 32];
    getrandom::fill(&mut bytes).map_err(|e| anyhow::anyhow!("cannot get random bytes from the operating system for a token: {e}"))?;
    Ok(hex::encode(bytes))
}

/// Writes `token` into a new file only its owner can read (mode 0600), replacing an old one.
pub(crate) fn write_private(path: &Path, token: &str) -> Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let _ = std::fs::remove_file(path);
    let mut f = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(path)
        .with_context(|| format!("cannot create {}", path.display()))?;
    f.write_all(token.as_bytes())?;
    f.sync_all()?;
    Ok(())
}

/// The token in `<state>/token`, generated (256 bits from the operating system, mode 0600)
/// when missing.
pub(crate) fn generated_token(state: &Path) -> Result<String> {
    let path = state.join("token");
    if path.exists() {
        return read_token(&path);
    }
    let token = random_token()?;
    write_private(&path, &token)?;
    tracing::info!("generated a bearer token in {} (pass it with --token-file)", path.display());
    Ok(token)
}

/// What a token may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, strum::IntoStaticStr)]
#[serde(rename_all = "lowercase")]
#[strum(serialize_all = "lowercase")]
pub enum Role {
    /// Everything: every job, draining workers, metrics; may also register workers.
    Admin,
    /// Submits jobs and sees, fetches and cancels its own.
    User,
    /// Registers and heartbeats MD workers, nothing else.
    Worker,
}

impl Role {
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

/// Per-user limits, checked at submit; `None`: no limit.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Limits {
    /// Jobs queued or running at once.
    pub max_jobs: Option<u64>,
    /// Bytes uploaded with one job (the scene and the files it names).
    pub max_upload_bytes: Option<u64>,
    /// Snapshots one job writes (`output.snapshots`).
    pub max_snapshots: Option<u64>,
}

impl Limits {
    /// These limits where set, `defaults` where not.
    pub fn over(self, defaults: Limits) -> Limits {
        Limits {
            max_jobs: self.max_jobs.or(defaults.max_jobs),
            max_upload_bytes: self.max_upload_bytes.or(defaults.max_upload_bytes),
            max_snapshots: self.max_snapshots.or(defaults.max_snapshots),
        }
    }
}

/// A user of the users file.
#[derive(Debug, Clone)]
pub struct User {
    pub name: String,
    pub role: Role,
    hash: [u8; 32],
    pub limits: Limits,
}

impl User {
    /// A user whose token is `token`.
    pub fn with_token(name: &str, role: Role, token: &str) -> User {
        User { name: name.to_string(), role, hash: Sha256::digest(token.as_bytes()).into(), limits: Limits::default() }
    }
}

/// Who made a call.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Caller {
    pub user: String,
    pub role: Role,
    pub limits: Limits,
}

impl Caller {
    pub fn is_admin(&self) -> bool {
        self.role == Role::Admin
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct UsersFile {
    #[serde(default)]
    user: Vec<UserEntry>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct UserEntry {
    name: String,
    role: Role,
    token_sha256: String,
    max_jobs: Option<u64>,
    max_upload_bytes: Option<u64>,
    max_snapshots: Option<u64>,
}

/// The users of a users file's text (`file` names it in messages).
pub fn parse_users(text: &str, file: &str) -> Result<Vec<User>> {
    let parsed: UsersFile = toml::from_str(text).map_err(|e| anyhow::anyhow!("users file {file}: {e}"))?;
    if parsed.user.is_empty() {
        bail!("users file {file} names no user: add [[user]] tables with name, role and token_sha256");
    }
    let mut users: Vec<User> = Vec::new();
    for (k, e) in parsed.user.into_iter().enumerate() {
        let at = format!("users file {file}, user {} ({:?})", k + 1, e.name);
        if e.name.is_empty() || e.name.len() > 64 || !e.name.chars().all(|c| c.is_ascii_alphanumeric() || "._-@".contains(c)) {
            bail!("{at}: name must be 1 to 64 letters, digits or ._-@");
        }
        let hex_hash = e.token_sha256.trim().to_ascii_lowercase();
        let hex_hash = hex_hash.strip_prefix("sha256:").unwrap_or(&hex_hash);
        let hash: [u8; 32] = hex::decode(hex_hash)
            .ok()
            .and_then(|b| b.try_into().ok())
            .with_context(|| format!("{at}: token_sha256 {:?} is not 64 hex digits (the SHA-256 of the token)", e.token_sha256))?;
        if users.iter().any(|u| u.name == e.name) {
            bail!("{at}: the name is given twice");
        }
        if users.iter().any(|u| u.hash == hash) {
            bail!("{at}: the same token_sha256 as another user (every user needs its own token)");
        }
        if e.max_jobs == Some(0) {
            bail!("{at}: max_jobs = 0 would refuse every job; remove the user instead");
        }
        users.push(User {
            name: e.name,
            role: e.role,
            hash,
            limits: Limits { max_jobs: e.max_jobs, max_upload_bytes: e.max_upload_bytes, max_snapshots: e.max_snapshots },
        });
    }
    Ok(users)
}

/// Reads a users file.
pub fn read_users(path: &Path) -> Result<Vec<User>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read the users file {}", path.display()))?;
    parse_users(&text, &path.display().to_string())
}

/// Who may call: the users, and where they came from.
pub struct Users {
    users: Vec<User>,
    /// The users file (None: the single-token mode).
    file: Option<PathBuf>,
    /// Users that are not in the file (the local workers' token), kept over reloads.
    extra: Vec<User>,
    /// The server's limits, under each user's own.
    pub defaults: Limits,
}

impl Users {
    /// The single-token mode: `token` is the admin user `admin`; read-only calls need no token.
    pub fn single(token: &str, defaults: Limits) -> Users {
        Users { users: vec![User::with_token("admin", Role::Admin, token)], file: None, extra: Vec::new(), defaults }
    }

    /// The users of `file`, and `extra` (kept when the file is read again).
    pub fn from_file(file: &Path, extra: Vec<User>, defaults: Limits) -> Result<Users> {
        let users = read_users(file)?;
        Ok(Users { users, file: Some(file.to_path_buf()), extra, defaults })
    }

    /// Reads the users file again (SIGHUP); on an error the users in force stay. Returns the
    /// number of users now.
    pub fn reload(&mut self) -> Result<usize> {
        let Some(file) = &self.file else { return Ok(self.users.len()) };
        self.users = read_users(file)?;
        Ok(self.users.len())
    }

    /// Whether calls that only read may come without a token (the single-token mode).
    pub fn anonymous_reads(&self) -> bool {
        self.file.is_none()
    }

    /// The user whose token is `given`: every user's hash is compared, each in constant time.
    pub fn find(&self, given: &str) -> Option<Caller> {
        let h: [u8; 32] = Sha256::digest(given.as_bytes()).into();
        let mut found = None;
        for u in self.users.iter().chain(&self.extra) {
            if constant_time_eq(&h, &u.hash) {
                found = Some(Caller { user: u.name.clone(), role: u.role, limits: u.limits.over(self.defaults) });
            }
        }
        found
    }
}

/// What a call needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Need {
    /// Read jobs or workers: an admin or a user (anyone in the single-token mode).
    Read,
    /// Submit or cancel jobs: an admin or a user.
    Jobs,
    /// Register or heartbeat a worker: a worker or an admin.
    Worker,
    /// Drain workers, read the metrics: an admin.
    Admin,
}

impl Core {
    /// Who `given` (the bearer token of a `call`, empty when none) is, if it may make the call.
    pub(crate) fn authorize(&self, given: &str, call: &str, need: Need) -> Result<Caller, JobError> {
        let users = super::shared::read(&self.users);
        if given.is_empty() {
            if need == Need::Read && users.anonymous_reads() {
                return Ok(Caller { user: "anonymous".into(), role: Role::Admin, limits: Limits::default() });
            }
            return Err(JobError::NoToken { call: call.to_string() });
        }
        let caller = users.find(given).ok_or_else(|| JobError::WrongToken { call: call.to_string() })?;
        let allowed = match need {
            Need::Read | Need::Jobs => caller.role != Role::Worker,
            Need::Worker => caller.role != Role::User,
            Need::Admin => caller.role == Role::Admin,
        };
        if !allowed {
            let why = match need {
                Need::Read | Need::Jobs => "a worker token may only register and heartbeat workers",
                Need::Worker => "only worker and admin tokens register and heartbeat workers",
                Need::Admin => "this needs an admin token",
            };
            return Err(JobError::Forbidden { call: call.to_string(), user: caller.user, role: caller.role.as_str(), why });
        }
        Ok(caller)
    }

    /// Reads the users file again (SIGHUP).
    pub(crate) fn reload_users(&self) {
        let mut users = super::shared::write(&self.users);
        match users.reload() {
            Ok(n) => tracing::info!("SIGHUP: read the users file again: {n} users"),
            Err(e) => tracing::error!("SIGHUP: {e:#}; the users in force are kept"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_compare_whole() {
        assert!(constant_time_eq(b"abc", b"abc"));
        assert!(!constant_time_eq(b"abc", b"abd"));
        assert!(!constant_time_eq(b"abc", b"ab"));
    }

    #[test]
    fn a_generated_token_is_kept_private_and_reused() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let state = dir.path().join("state");
        let t = generated_token(&state).unwrap();
        assert_eq!(t.len(), 64);
        assert!(t.chars().all(|c| c.is_ascii_hexdigit()));
        assert_eq!(std::fs::metadata(state.join("token")).unwrap().permissions().mode() & 0o777, 0o600);
        assert_eq!(generated_token(&state).unwrap(), t);
        assert_ne!(generated_token(&dir.path().join("other")).unwrap(), t);
    }

    fn sha(t: &str) -> String {
        hex::encode(Sha256::digest(t.as_bytes()))
    }

    #[test]
    fn users_are_found_by_their_token_with_their_role_and_limits() {
        let text = format!(
            "[[user]]\nname = \"alice\"\nrole = \"user\"\ntoken_sha256 = \"{}\"\nmax_jobs = 2\n\n[[user]]\nname = \"root\"\nrole = \"admin\"\ntoken_sha256 = \"sha256:{}\"\n\n[[user]]\nname = \"w\"\nrole = \"worker\"\ntoken_sha256 = \"{}\"\n",
            sha("ta"),
            sha("tr").to_uppercase(),
            sha("tw")
        );
        let users = parse_users(&text, "u.toml").unwrap();
        let defaults = Limits { max_jobs: Some(9), max_upload_bytes: Some(100), max_snapshots: None };
        let u = Users { users, file: Some("u.toml".into()), extra: vec![User::with_token("local", Role::Worker, "tl")], defaults };
        let a = u.find("ta").unwrap();
        assert_eq!((a.user.as_str(), a.role), ("alice", Role::User));
        assert_eq!(a.limits, Limits { max_jobs: Some(2), max_upload_bytes: Some(100), max_snapshots: None });
        assert_eq!(u.find("tr").unwrap().role, Role::Admin);
        assert_eq!(u.find("tw").unwrap().role, Role::Worker);
        assert_eq!(u.find("tl").unwrap().user, "local");
        assert!(u.find("t").is_none() && u.find("").is_none() && u.find("ta ").is_none());
        assert!(!u.anonymous_reads());
        assert!(Users::single("x", Limits::default()).anonymous_reads());
    }

    #[test]
    fn a_broken_users_file_is_refused_naming_the_user_and_the_key() {
        let one =
            |name: &str, role: &str, hash: &str| format!("[[user]]\nname = \"{name}\"\nrole = \"{role}\"\ntoken_sha256 = \"{hash}\"\n");
        let good = sha("a");
        for (text, expect) in [
            (String::new(), "names no user"),
            (one("alice", "boss", &good), "unknown variant `boss`"),
            (one("alice", "user", "abc"), "is not 64 hex digits"),
            (one("al ice", "user", &good), "name must be"),
            (one("alice", "user", &good) + &one("alice", "user", &sha("b")), "the name is given twice"),
            (one("alice", "user", &good) + &one("bob", "user", &good), "the same token_sha256"),
            (one("alice", "user", &good) + "colour = 1\n", "unknown field `colour`"),
            (one("alice", "user", &good) + "max_jobs = 0\n", "max_jobs = 0"),
            ("[[user]]\nname = \"alice\"\n".to_string(), "missing field `role`"),
        ] {
            let e = format!("{:#}", parse_users(&text, "u.toml").unwrap_err());
            assert!(e.contains("u.toml") && e.contains(expect), "{text:?}: {e}");
        }
    }

    #[test]
    fn a_reload_keeps_the_users_in_force_when_the_file_is_broken() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("users.toml");
        std::fs::write(&f, format!("[[user]]\nname = \"a\"\nrole = \"user\"\ntoken_sha256 = \"{}\"\n", sha("ta"))).unwrap();
        let mut u = Users::from_file(&f, vec![User::with_token("local", Role::Worker, "tl")], Limits::default()).unwrap();
        assert!(u.find("ta").is_some() && u.find("tb").is_none());
        std::fs::write(&f, format!("[[user]]\nname = \"b\"\nrole = \"admin\"\ntoken_sha256 = \"{}\"\n", sha("tb"))).unwrap();
        assert_eq!(u.reload().unwrap(), 1);
        assert!(u.find("ta").is_none() && u.find("tb").is_some() && u.find("tl").is_some());
        std::fs::write(&f, "not toml [").unwrap();
        assert!(u.reload().is_err());
        assert!(u.find("tb").is_some());
    }
}
