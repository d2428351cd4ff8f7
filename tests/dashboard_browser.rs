//! The dashboard in a real browser: headless Chromium (Debian's `chromium`, `bash
//! deploy/setup.sh browser`) loads a job's page while the job runs; the page follows the job's
//! server-sent events to its end (Chromium's virtual-time budget waits while the event stream
//! is open, and the page closes it after the final event), and what the page then shows (state,
//! step, digest, progress, the number of result files, that it saw the end live) is checked
//! against the job store; a screenshot of the finished page is saved under the target
//! directory (`target/tmp/dashboard.png`, path printed).
//!
//! Ignored unless MSCALE_REQUIRE_BROWSER=1 (then a missing chromium fails it). Needs the
//! prebuilt `mscale` (`cargo build --profile test -p orchestrator --bin mscale`).

// A panic is how these tests report a failure.
#![allow(clippy::unwrap_used)]

use mscale_testkit::{Proc, text};
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const TOKEN: &str = "browser-token-0123456789";

fn chromium() -> PathBuf {
    for c in ["chromium", "chromium-browser", "google-chrome"] {
        if let Ok(o) = Command::new("sh").args(["-c", &format!("command -v {c}")]).output()
            && o.status.success()
        {
            return PathBuf::from(String::from_utf8_lossy(&o.stdout).trim());
        }
    }
    panic!("no chromium: run `bash deploy/setup.sh browser`");
}

fn headless(args: &[&str]) -> std::process::Output {
    let home = tempfile::tempdir().unwrap();
    Command::new(chromium())
        .args(["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-dev-shm-usage", "--hide-scrollbars"])
        .arg(format!("--user-data-dir={}", home.path().display()))
        .args(args)
        .env("HOME", home.path())
        .output()
        .unwrap()
}

/// The value of `attr="..."` in the element with `id="ID"`.
fn attr(dom: &str, id: &str, attr: &str) -> Option<String> {
    let at = dom.find(&format!("id=\"{id}\""))?;
    let start = dom[..at].rfind('<')?;
    let end = at + dom[at..].find('>')?;
    let tag = &dom[start..end];
    let k = tag.find(&format!(" {attr}=\""))? + attr.len() + 3;
    Some(tag[k..k + tag[k..].find('"')?].to_string())
}

/// The text of the element with `id="ID"` (up to its first child tag).
fn inner(dom: &str, id: &str) -> Option<String> {
    let at = dom.find(&format!("id=\"{id}\""))?;
    let open = at + dom[at..].find('>')? + 1;
    Some(dom[open..open + dom[open..].find('<')?].to_string())
}

#[test]
#[cfg_attr(not(require_browser), ignore = "needs chromium: bash deploy/setup.sh browser; runs with MSCALE_REQUIRE_BROWSER=1 (CI)")]
fn the_job_page_follows_a_running_job_to_its_end_in_chromium() {
    let (tmp, token_file) = mscale_testkit::token_dir(TOKEN);
    let mscale = mscale_testkit::prebuilt("mscale", "orchestrator");
    let mut cmd = Command::new(&mscale);
    cmd.args(["serve", "--state", tmp.path().join("state").to_str().unwrap(), "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"])
        .args(["--token-file", token_file.to_str().unwrap()])
        .env("RUST_LOG", "info")
        .stdout(Stdio::piped());
    let mut server = Proc::spawn_logged(&mut cmd, &tmp.path().join("serve.log"));
    let mut out = BufReader::new(server.child.stdout.take().unwrap());
    let mut line = String::new();
    out.read_line(&mut line).unwrap();
    let grpc = line.trim().strip_prefix("mscale serve: listening on ").unwrap_or_else(|| panic!("{line}")).to_string();
    line.clear();
    out.read_line(&mut line).unwrap();
    let http = line.trim().strip_prefix("mscale serve: dashboard and metrics on ").unwrap_or_else(|| panic!("{line}")).to_string();
    // A coupled job of several seconds (md-small, 32 points, 1200 steps, MD in the orchestrator:
    // about 7 s on two cores), long enough that Chromium starts and loads the page while it runs
    // (300 steps, under a second since the intra-box threads, once ended before the page loaded).
    let o = Command::new(&mscale)
        .args(["submit", "tests/data/md-small.toml", "--server", &grpc, "--token-file", token_file.to_str().unwrap()])
        .args(["--set", "domain.cells=[32]", "--set", "scheme.end_time=1.2e-11"])
        .current_dir(mscale_testkit::repo())
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let id = String::from_utf8(o.stdout).unwrap().trim().to_string();
    let mut client = orchestrator::client::Client::connect(&grpc, None).unwrap();
    let start = Instant::now();
    while client.get(&id).unwrap().step == 0 {
        assert!(start.elapsed() < Duration::from_secs(60), "the job did not start; log: {}", server.log());
        std::thread::sleep(Duration::from_millis(20));
    }
    let before = client.get(&id).unwrap();
    assert!(before.step < before.steps, "the job ended before the browser could load its page");
    let url = format!("{http}/jobs/{id}?token={TOKEN}");
    let shown = headless(&["--virtual-time-budget=300000", "--dump-dom", &url]);
    let dom = String::from_utf8_lossy(&shown.stdout).into_owned();
    assert!(shown.status.success() && dom.contains("id=\"job\""), "chromium: {}", text(&shown));
    let job = client.get(&id).unwrap();
    assert_eq!(job.state, mscale_proto::orchestrator::v1::JobState::Completed as i32, "{job:?}");
    // What the page shows, from the events it received live, against the store.
    assert_eq!(attr(&dom, "job", "data-live-final").as_deref(), Some("1"), "the page did not see the end live:\n{dom}");
    assert_eq!(attr(&dom, "job", "data-state").as_deref(), Some("completed"));
    assert_eq!(inner(&dom, "state").as_deref(), Some("completed"));
    assert_eq!(inner(&dom, "step"), Some(format!("{0} / {0}", job.steps)));
    assert_eq!(attr(&dom, "bar", "value").map(|v| v.parse::<f64>().unwrap()), Some(100.0), "{dom}");
    let received: u64 = attr(&dom, "job", "data-received").unwrap().parse().unwrap();
    let seq: u64 = attr(&dom, "job", "data-seq").unwrap().parse().unwrap();
    let mut last = 0;
    client.watch(&id, |e| last = e.sequence).unwrap();
    assert_eq!((received, seq), (last, last), "the page got every event once");
    let run = tmp.path().join("state/jobs").join(&id).join("run").canonicalize().unwrap();
    let files = orchestrator::service::run_files(&run).unwrap();
    assert_eq!(attr(&dom, "nfiles", "data-n"), Some(files.len().to_string()), "{dom}");
    assert!(dom.contains(&format!("href=\"/jobs/{id}/files/summary.json\"")));
    // A picture of the finished page.
    let png = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("dashboard.png");
    let _ = std::fs::remove_file(&png);
    let shot = headless(&["--window-size=1100,1500", "--virtual-time-budget=5000", &format!("--screenshot={}", png.display()), &url]);
    assert!(png.metadata().is_ok_and(|m| m.len() > 10_000), "no screenshot: {}", text(&shot));
    eprintln!("screenshot of the job page: {}", png.display());
}
