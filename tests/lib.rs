//! Helpers shared by the integration tests.

use std::path::PathBuf;

/// Root of the repository.
pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A small valid 1D scene (ideal-gas shock tube, 50 cells) to mutate in tests.
pub fn small_scene() -> String {
    std::fs::read_to_string(repo().join("tests/data/small.toml")).expect("tests/data/small.toml")
}

/// Path of a workspace binary (`mscale`, `md-worker`), brought up to date by `cargo build`
/// once per test process (a no-op when fresh), so `cargo test -p mscale-tests` never runs a
/// stale binary.
pub fn binary(name: &str, package: &str) -> PathBuf {
    static BUILT: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());
    let mut dir = std::env::current_exe().expect("test executable path");
    dir.pop();
    if dir.ends_with("deps") {
        dir.pop();
    }
    let path = dir.join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    let mut built = BUILT.lock().unwrap_or_else(|p| p.into_inner());
    if !built.iter().any(|b| b == name) {
        let mut cmd = std::process::Command::new(env!("CARGO"));
        cmd.args(["build", "-q", "-p", package, "--bin", name]).current_dir(repo());
        if dir.ends_with("release") {
            cmd.arg("--release");
        }
        let status = cmd.status().expect("run cargo build");
        assert!(status.success(), "cargo build -p {package} --bin {name} failed");
        built.push(name.to_string());
    }
    path
}

/// A running `md-worker serve` on a free loopback port, killed on drop.
pub struct Worker {
    pub child: std::process::Child,
    pub addr: String,
}

impl Worker {
    pub fn start(threads: usize) -> Worker {
        use std::io::BufRead;
        let mut child = std::process::Command::new(binary("md-worker", "md-worker"))
            .args(["serve", "--listen", "127.0.0.1:0", "--threads", &threads.to_string()])
            .env("RUST_LOG", "warn")
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("start md-worker serve");
        let stdout = child.stdout.take().expect("stdout");
        let mut line = String::new();
        std::io::BufReader::new(stdout).read_line(&mut line).expect("read the listening line");
        let addr = line.trim().strip_prefix("listening on ").unwrap_or_else(|| panic!("unexpected first line {line:?}")).to_string();
        Worker { child, addr }
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
