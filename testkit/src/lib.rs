//! The process-spawning helpers shared by the integration tests of every mscale crate
//! (orchestrator/tests, md-worker/tests, tests/): finding a workspace binary without building
//! it, child processes that die with the test, servers that announce their address on their
//! first line, signals, the text of an output, run summaries and their digests.
//!
//! It depends on no crate of the workspace, so any of them can take it as a dev-dependency.
//!
//! # Binaries: no test runs `cargo build`
//! A test of the package that owns a binary names it with `env!("CARGO_BIN_EXE_<name>")`
//! (cargo builds it before the test). Every other binary is prebuilt: [`prebuilt`] takes it
//! from the target directory the test itself runs from (`target/debug`, `target/release`), or
//! from the directory in `MSCALE_BIN_DIR`. `cargo test --workspace` builds every binary of
//! the workspace before it runs any test; the tests of one package alone need the binary
//! built first with the command the panic message names, e.g.
//! `cargo build --profile test -p orchestrator --bin mscale`. A binary older than one of its
//! source files (by cargo's dep-info file next to it, `mscale.d`, which that command writes)
//! is refused the same way. A binary that cargo built only for another package's tests has no
//! such file (cargo writes none then) and is taken as it is: build it with that command, or
//! run `cargo test --workspace`, which rebuilds whatever is stale before any test runs.

pub mod fuzz;

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant, SystemTime};

/// Root of the workspace.
pub fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("the testkit lies inside the workspace").to_path_buf()
}

/// The directory holding the workspace's binaries for the running test: `MSCALE_BIN_DIR`, or
/// the target directory of the test executable (`target/debug/deps/x-123` -> `target/debug`).
pub fn bin_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("MSCALE_BIN_DIR").filter(|d| !d.is_empty()) {
        return PathBuf::from(d);
    }
    let mut dir = std::env::current_exe().expect("the test executable's path");
    dir.pop();
    if dir.ends_with("deps") {
        dir.pop();
    }
    dir
}

/// The prebuilt binary `name` of workspace package `package` (see the crate doc): panics,
/// naming the command that builds it, when it is missing or older than one of its sources.
pub fn prebuilt(name: &str, package: &str) -> PathBuf {
    let dir = bin_dir();
    let path = dir.join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    let profile = if dir.ends_with("release") { "--release" } else { "--profile test" };
    let build = format!("cargo build {profile} -p {package} --bin {name}");
    if !path.is_file() {
        panic!(
            "{} does not exist: build it first with `{build}` (`cargo test --workspace` builds every binary before its tests; MSCALE_BIN_DIR names another directory)",
            path.display()
        );
    }
    if let Some(newer) = stale_source(&path) {
        panic!("{} is older than its source {}: rebuild it with `{build}` (no test runs cargo itself)", path.display(), newer.display());
    }
    path
}

/// A source of `bin` (listed in cargo's dep-info file `bin.d`, inside this workspace but
/// outside the target directory) that is newer than it; None when it is up to date or there
/// is no dep-info file. Listed files that do not exist are passed over (a build script's
/// `rerun-if-changed` may name a file that is absent, such as `.git/HEAD` in a worktree).
pub fn stale_source(bin: &Path) -> Option<PathBuf> {
    let built = std::fs::metadata(bin).and_then(|m| m.modified()).ok()?;
    let deps = std::fs::read_to_string(bin.with_extension("d")).ok()?;
    let root = repo().canonicalize().ok()?;
    let target = bin.parent()?.parent()?.canonicalize().ok()?;
    for line in deps.lines() {
        let Some((_, list)) = line.split_once(": ") else { continue };
        // Makefile syntax: paths separated by spaces, a space inside a path escaped as "\ ".
        let list = list.replace("\\ ", "\u{0}");
        for dep in list.split_whitespace().map(|d| PathBuf::from(d.replace('\u{0}', " "))) {
            if !dep.starts_with(&root) || dep.starts_with(&target) {
                continue;
            }
            let changed = std::fs::metadata(&dep).and_then(|m| m.modified()).unwrap_or(SystemTime::UNIX_EPOCH);
            if changed > built {
                return Some(dep);
            }
        }
    }
    None
}

/// A child process that is killed (and reaped) when dropped, with an optional log file (where
/// its stderr went).
pub struct Proc {
    pub child: Child,
    pub log: Option<PathBuf>,
    /// On drop: SIGTERM first and up to 10 s to exit (mpirun, which passes it to its ranks).
    pub terminate_first: bool,
}

impl Proc {
    /// Starts `cmd` as is.
    pub fn spawn(cmd: &mut Command) -> Proc {
        let child = cmd.spawn().unwrap_or_else(|e| panic!("cannot start {:?}: {e}", cmd.get_program()));
        Proc { child, log: None, terminate_first: false }
    }

    /// Starts `cmd` with its stderr written to `log`.
    pub fn spawn_logged(cmd: &mut Command, log: &Path) -> Proc {
        let file = std::fs::File::create(log).unwrap_or_else(|e| panic!("{}: {e}", log.display()));
        let mut p = Proc::spawn(cmd.stderr(file));
        p.log = Some(log.to_path_buf());
        p
    }

    /// What the process wrote to its log so far (empty without one).
    pub fn log(&self) -> String {
        self.log.as_ref().and_then(|l| std::fs::read_to_string(l).ok()).unwrap_or_default()
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Sends a signal with kill(1): `"-KILL"`, `"-STOP"`, `"-CONT"`, `"-TERM"`.
    pub fn signal(&self, sig: &str) {
        let ok = Command::new("kill").args([sig, &self.pid().to_string()]).status().is_ok_and(|s| s.success());
        assert!(ok, "kill {sig} {} failed", self.pid());
    }

    /// Waits up to `limit` for the process to exit.
    pub fn wait_exit(&mut self, limit: Duration) -> Option<std::process::ExitStatus> {
        let start = Instant::now();
        loop {
            if let Ok(Some(s)) = self.child.try_wait() {
                return Some(s);
            }
            if start.elapsed() > limit {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        if self.terminate_first {
            let _ = Command::new("kill").args(["-TERM", &self.pid().to_string()]).status();
            if self.wait_exit(Duration::from_secs(10)).is_some() {
                return;
            }
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A process that announced where it listens on its first line of stdout.
pub struct Listening {
    pub proc: Proc,
    pub addr: String,
}

impl Listening {
    /// Starts `cmd` with stdout piped (and stderr into `log`, if given) and reads its first
    /// line, which must be `prefix` followed by the address; panics with the line and the log
    /// otherwise.
    pub fn start(cmd: &mut Command, prefix: &str, log: Option<&Path>) -> Listening {
        cmd.stdout(Stdio::piped());
        let mut proc = match log {
            Some(l) => Proc::spawn_logged(cmd, l),
            None => Proc::spawn(cmd),
        };
        let stdout = proc.child.stdout.take().expect("stdout is piped");
        let mut line = String::new();
        std::io::BufReader::new(stdout).read_line(&mut line).expect("read the first line");
        let addr = match line.trim().strip_prefix(prefix) {
            Some(a) => a.to_string(),
            None => panic!("{:?}: unexpected first line {line:?} (expected {prefix:?}...); log: {}", cmd.get_program(), proc.log()),
        };
        Listening { proc, addr }
    }

    /// `md-worker serve --listen 127.0.0.1:0 --threads N` (RUST_LOG=warn) from `exe`.
    pub fn md_worker(exe: &Path, threads: usize) -> Listening {
        let mut cmd = Command::new(exe);
        cmd.args(["serve", "--listen", "127.0.0.1:0", "--threads", &threads.to_string()]).env("RUST_LOG", "warn");
        Listening::start(&mut cmd, "listening on ", None)
    }
}

/// stdout and stderr of an output, for assertion messages.
pub fn text(o: &Output) -> String {
    format!("stdout: {}\nstderr: {}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// `s` without ANSI colour codes.
pub fn plain(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut chars = s.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            chars.by_ref().find(|c| c.is_ascii_alphabetic());
        } else {
            out.push(c);
        }
    }
    out
}

/// A run directory's summary.json.
pub fn summary(dir: &Path) -> serde_json::Value {
    let path = dir.join("summary.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The `state_digest` of a completed run.
pub fn state_digest(dir: &Path) -> String {
    let s = summary(dir);
    assert_eq!(s["status"], "completed", "{s}");
    s["state_digest"].as_str().unwrap_or_else(|| panic!("no state_digest: {s}")).to_string()
}

/// A temporary directory holding the file `token` with `token` in it (and a newline).
pub fn token_dir(token: &str) -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().expect("tempdir");
    let file = tmp.path().join("token");
    std::fs::write(&file, format!("{token}\n")).expect("write the token");
    (tmp, file)
}

/// Polls `done` every 10 ms until it holds; panics with `what` after `limit`.
pub fn wait_until(what: &str, limit: Duration, mut done: impl FnMut() -> bool) {
    let start = Instant::now();
    while !done() {
        assert!(start.elapsed() < limit, "{what}: not within {limit:?}");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// An HTTP response as [`http_get`] reads it.
#[derive(Debug, Clone)]
pub struct HttpResponse {
    pub status: u16,
    /// Header names in lower case, in order.
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl HttpResponse {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }

    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// `GET path` over plain HTTP/1.1 to `addr` (HOST:PORT) with `headers`, `Connection: close`,
/// read to the end (a chunked body is decoded), within `limit`.
pub fn http_get(addr: &str, path: &str, headers: &[(&str, &str)], limit: Duration) -> std::io::Result<HttpResponse> {
    use std::io::{Read, Write};
    let bad = |what: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, format!("GET {path} from {addr}: {what}"));
    let mut s = std::net::TcpStream::connect(addr)?;
    s.set_read_timeout(Some(limit))?;
    let mut req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    s.write_all(req.as_bytes())?;
    let mut raw = Vec::new();
    s.read_to_end(&mut raw)?;
    let end = raw.windows(4).position(|w| w == b"\r\n\r\n").ok_or_else(|| bad("no end of the headers"))?;
    let head = String::from_utf8_lossy(&raw[..end]).into_owned();
    let mut lines = head.split("\r\n");
    let status = lines.next().and_then(|l| l.split_whitespace().nth(1)).and_then(|c| c.parse().ok()).ok_or_else(|| bad("no status"))?;
    let headers: Vec<(String, String)> =
        lines.filter_map(|l| l.split_once(':')).map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string())).collect();
    let mut body = raw[end + 4..].to_vec();
    if headers.iter().any(|(k, v)| k == "transfer-encoding" && v.contains("chunked")) {
        let (mut out, mut rest) = (Vec::new(), &body[..]);
        loop {
            let nl = rest.windows(2).position(|w| w == b"\r\n").ok_or_else(|| bad("a chunk without its size line"))?;
            let size = usize::from_str_radix(String::from_utf8_lossy(&rest[..nl]).split(';').next().unwrap_or("").trim(), 16)
                .map_err(|_| bad("a bad chunk size"))?;
            rest = &rest[nl + 2..];
            if size == 0 {
                break;
            }
            out.extend_from_slice(rest.get(..size).ok_or_else(|| bad("a chunk cut short"))?);
            rest = rest.get(size + 2..).unwrap_or(&[]);
        }
        body = out;
    }
    Ok(HttpResponse { status, headers, body })
}

/// The samples of a Prometheus text exposition: (name, labels, value).
pub fn prometheus_samples(text: &str) -> Vec<(String, std::collections::BTreeMap<String, String>, f64)> {
    let mut out = Vec::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')) {
        let (series, value) = match line.rsplit_once(' ') {
            Some(x) => x,
            None => continue,
        };
        let value = match value {
            "+Inf" => f64::INFINITY,
            "-Inf" => f64::NEG_INFINITY,
            v => v.parse().unwrap_or(f64::NAN),
        };
        let (name, labels) = match series.split_once('{') {
            Some((n, rest)) => (n, rest.trim_end_matches('}')),
            None => (series, ""),
        };
        let mut map = std::collections::BTreeMap::new();
        // Label values here never hold `",` (ids, states, methods, addresses).
        for kv in labels.split("\",").filter(|kv| !kv.is_empty()) {
            if let Some((k, v)) = kv.split_once('=') {
                map.insert(k.trim_matches(',').to_string(), v.trim_matches('"').to_string());
            }
        }
        out.push((name.to_string(), map, value));
    }
    out
}

/// A certificate authority `ca.pem` and a server certificate `server.pem` (key `server.key`)
/// for localhost and 127.0.0.1 in `dir`, made with openssl; returns the three paths.
pub fn tls_certificates(dir: &Path) -> (PathBuf, PathBuf, PathBuf) {
    let run = |args: &[&str]| {
        let o = Command::new("openssl").args(args).current_dir(dir).output().expect("openssl is needed for the TLS tests");
        assert!(o.status.success(), "openssl {args:?}: {}", text(&o));
    };
    let ca = [
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-days",
        "2",
        "-subj",
        "/CN=mscale test CA",
    ];
    run(&ca);
    run(&["req", "-newkey", "rsa:2048", "-nodes", "-keyout", "server.key", "-out", "server.csr", "-subj", "/CN=localhost"]);
    std::fs::write(dir.join("san.ext"), "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n").expect("write san.ext");
    let sign = ["x509", "-req", "-in", "server.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial", "-out", "server.pem"];
    run(&[&sign[..], &["-days", "2", "-extfile", "san.ext"]].concat());
    (dir.join("ca.pem"), dir.join("server.pem"), dir.join("server.key"))
}
