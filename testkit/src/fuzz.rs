//! Mutation fuzzing of the parsers a user or a peer reaches (scene TOML and `--set`, checkpoint
//! files, the tokens file, the protobuf messages the servers decode).
//!
//! No coverage instrumentation is reachable on the stable toolchain here, so the loop is
//! guided by outcomes instead: every input is put through the target's real code, which
//! answers with an outcome class (`"ok"`, or the error message with its numbers blanked);
//! an input that gives a class not seen before joins the corpus and is mutated further, so
//! the corpus holds one input per distinct behaviour reached. The corpus lives in
//! `tests/fuzz-corpus/<target>/` of the crate (committed, small), is read at start, and is
//! written back when `MSCALE_FUZZ_SAVE=1` (the long runs).
//!
//! The streams are deterministic (ChaCha from the target's name and `MSCALE_FUZZ_SEED`), and a
//! target runs a fixed number of mutations ([`Budget`]: its own default, or
//! `MSCALE_FUZZ_ITERS`), so the test command and CI put the same inputs through on every
//! machine, fast or slow; `MSCALE_FUZZ_SECS` turns that into a time budget for the long
//! exploratory runs. A failure names what reproduces it. A panic in the check fails the test with the input's file (it is written under the
//! temporary directory before each check, so an abort leaves it too); a check running past the
//! hang limit (`MSCALE_FUZZ_HANG_SECS`, default 60) or a resident size past the memory bound
//! (`MSCALE_FUZZ_MAX_RSS_MB`, default 3072, of this process and of a watched server) aborts
//! the process with the same file named. With `MSCALE_FUZZ_LOG=1` a line of figures (inputs,
//! inputs/s, corpus, classes, peak memory) is appended to `tests/fuzz-corpus/MEASUREMENTS.md`.

pub use rand::Rng;
use rand::SeedableRng;
use rand_chacha::ChaCha20Rng;
use std::collections::BTreeSet;
use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::time::{Duration, Instant};

pub type Rng64 = ChaCha20Rng;

/// Numbers and words that broke parsers somewhere.
pub const HOSTILE: &[&str] = &[
    "nan",
    "NaN",
    "inf",
    "-inf",
    "0",
    "-0",
    "0.0",
    "1e308",
    "-1e308",
    "1e-308",
    "5e-324",
    "-1",
    "1",
    "2",
    "5",
    "4294967295",
    "4294967296",
    "9223372036854775807",
    "-9223372036854775808",
    "18446744073709551615",
    "99999999999999999999",
    "100000000000",
    "1e12",
    "0x10",
    "",
    "1e",
    "-",
    "+",
    ".",
    "\"\"",
    "\"x\"",
    "\"../../../../etc/passwd\"",
    "\"/dev/zero\"",
    "\"\u{fffd}\"",
    "[]",
    "[1e308, -1e308]",
    "[[]]",
    "{}",
    "true",
    "false",
    "=",
    "[",
    "]",
    "[[bodies]]",
    "[scheme]",
    "#",
    "'''",
    "\"\"\"",
    "\\",
];

fn env_f64(name: &str, default: f64) -> f64 {
    std::env::var(name).ok().and_then(|s| s.parse().ok()).unwrap_or(default)
}

/// How long a fuzz target runs: a fixed number of mutations (the same inputs on any machine),
/// or, with `MSCALE_FUZZ_SECS` set, seconds (long runs: how far they get depends on the
/// machine, so a time budget is for exploring, not for the test command).
#[derive(Debug, Clone, Copy)]
pub enum Budget {
    Iterations(u64),
    Time(Duration),
}

impl Budget {
    /// `MSCALE_FUZZ_SECS` when set, else `MSCALE_FUZZ_ITERS` or the target's `default` count.
    pub fn from_env(default: u64) -> Budget {
        match std::env::var("MSCALE_FUZZ_SECS").ok().and_then(|s| s.parse::<f64>().ok()) {
            Some(s) => Budget::Time(Duration::from_secs_f64(s)),
            None => Budget::Iterations(std::env::var("MSCALE_FUZZ_ITERS").ok().and_then(|s| s.parse().ok()).unwrap_or(default)),
        }
    }

    /// Whether another mutation is due after `done` of them, `elapsed` into the run.
    pub fn more(&self, done: u64, elapsed: Duration) -> bool {
        match *self {
            Budget::Iterations(n) => done < n,
            Budget::Time(limit) => elapsed < limit,
        }
    }
}

fn fnv(bytes: &[u8]) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    bytes.hash(&mut h);
    h.finish()
}

/// An error message with its digits blanked and cut to 160 characters: the outcome class.
pub fn class_of(message: &str) -> String {
    let mut out = String::new();
    let mut last_digit = false;
    for c in message.chars() {
        if c.is_ascii_digit() {
            if !last_digit {
                out.push('#');
            }
            last_digit = true;
        } else {
            out.push(c);
            last_digit = false;
        }
        if out.len() >= 160 {
            break;
        }
    }
    out
}

/// Resident and peak resident size (bytes) of a process (`self` or a pid), from /proc.
pub fn rss_of(pid: &str) -> Option<(u64, u64)> {
    let s = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let field = |name: &str| -> Option<u64> {
        let l = s.lines().find(|l| l.starts_with(name))?;
        Some(l.split_whitespace().nth(1)?.parse::<u64>().ok()? * 1024)
    };
    Some((field("VmRSS:")?, field("VmHWM:")?))
}

/// What each thread of a process waits in (name, state, kernel wait channel, and its kernel
/// stack where readable), from /proc: printed when a server stops answering, so a hang seen
/// once in CI says where it stood.
pub fn threads_of(pid: u32) -> String {
    let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else { return format!("(no /proc/{pid}/task)") };
    let mut out = String::new();
    for t in tasks.flatten() {
        let p = t.path();
        let read = |f: &str| std::fs::read_to_string(p.join(f)).unwrap_or_default();
        let state = read("status").lines().find(|l| l.starts_with("State:")).unwrap_or_default().to_string();
        let stack: Vec<String> =
            read("stack").lines().take(8).map(|l| l.split_whitespace().last().unwrap_or_default().to_string()).collect();
        out.push_str(&format!(
            "  {} {:?} {} wchan={} {}\n",
            t.file_name().to_string_lossy(),
            read("comm").trim(),
            state.trim_start_matches("State:").trim(),
            read("wchan"),
            stack.join(" < ")
        ));
    }
    out.push_str(&user_stacks(pid));
    out
}

/// Each thread's frames in this workspace's code, from `gdb -batch` where it is installed (a
/// hung server's backtrace named both sides of a lock-order deadlock at once); empty otherwise.
fn user_stacks(pid: u32) -> String {
    let Ok(o) = std::process::Command::new("timeout")
        .args(["60", "gdb", "-p", &pid.to_string(), "-batch", "-ex", "thread apply all bt 40"])
        .stderr(std::process::Stdio::null())
        .output()
    else {
        return String::new();
    };
    let text = String::from_utf8_lossy(&o.stdout);
    let ours =
        |l: &str| l.contains(" at ") && l.contains("src/") && !l.contains("/rustc/") && !l.contains("library/") && !l.contains(".cargo/");
    let kept: Vec<&str> = text.lines().filter(|l| l.starts_with("Thread ") || (l.starts_with('#') && ours(l))).collect();
    if kept.is_empty() { String::new() } else { format!("gdb, this workspace's frames of each thread:\n{}\n", kept.join("\n")) }
}

/// A fuzz target: its corpus, its stream, its figures.
pub struct Fuzzer {
    pub name: String,
    pub rng: Rng64,
    pub corpus: Vec<Vec<u8>>,
    classes: BTreeSet<String>,
    dir: PathBuf,
    save: bool,
    current: PathBuf,
    /// A server process whose memory is bounded and reported too.
    pub watched_pid: Arc<AtomicU32>,
    max_corpus: usize,
    max_saved_len: usize,
    budget: Budget,
}

/// What a run of a target did.
#[derive(Debug, Clone)]
pub struct Report {
    pub iterations: u64,
    pub seconds: f64,
    pub corpus: usize,
    pub classes: usize,
    pub peak_rss: u64,
    pub peak_watched_rss: u64,
}

impl Fuzzer {
    /// A target named `name` whose corpus is `corpus_root/<name>/`, started from `seeds` and
    /// what the corpus directory holds, running `iterations` mutations unless the environment
    /// says otherwise ([`Budget::from_env`]).
    pub fn new(name: &str, corpus_root: &Path, seeds: Vec<Vec<u8>>, iterations: u64) -> Fuzzer {
        let dir = corpus_root.join(name);
        let mut corpus = seeds;
        if let Ok(entries) = std::fs::read_dir(&dir) {
            let mut files: Vec<PathBuf> = entries.flatten().map(|e| e.path()).filter(|p| p.is_file()).collect();
            files.sort();
            for f in files {
                if let Ok(b) = std::fs::read(&f) {
                    corpus.push(b);
                }
            }
        }
        assert!(!corpus.is_empty(), "fuzz target {name} has no seed input");
        let seed = std::env::var("MSCALE_FUZZ_SEED").ok().and_then(|s| s.parse::<u64>().ok()).unwrap_or(0);
        let current = std::env::temp_dir().join(format!("mscale-fuzz-{name}-{}.input", std::process::id()));
        Fuzzer {
            name: name.to_string(),
            rng: ChaCha20Rng::seed_from_u64(fnv(name.as_bytes()) ^ seed),
            corpus,
            classes: BTreeSet::new(),
            dir,
            save: std::env::var("MSCALE_FUZZ_SAVE").is_ok_and(|v| v == "1"),
            current,
            watched_pid: Arc::new(AtomicU32::new(0)),
            max_corpus: 96,
            max_saved_len: 12 << 10,
            budget: Budget::from_env(iterations),
        }
    }

    /// Runs mutations of the corpus through `check` for the target's [`Budget`]: `mutate` makes an input from
    /// a parent (and the whole corpus, to splice), `check` answers the outcome class of an
    /// input (a panic in it fails the test).
    pub fn run(
        &mut self,
        mut mutate: impl FnMut(&mut Rng64, &[u8], &[Vec<u8>]) -> Vec<u8>,
        mut check: impl FnMut(&[u8]) -> String,
    ) -> Report {
        let hang = Duration::from_secs_f64(env_f64("MSCALE_FUZZ_HANG_SECS", 60.0));
        let max_rss = (env_f64("MSCALE_FUZZ_MAX_RSS_MB", 3072.0) * 1048576.0) as u64;
        // The watchdog: a check past the hang limit, or memory past the bound, aborts.
        let started_ms = Arc::new(AtomicU64::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let peak_watched = Arc::new(AtomicU64::new(0));
        let t0 = Instant::now();
        let dog = {
            let (started_ms, stop, peak_watched, watched) =
                (started_ms.clone(), stop.clone(), peak_watched.clone(), self.watched_pid.clone());
            let (name, current) = (self.name.clone(), self.current.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(200));
                    let s = started_ms.load(Ordering::SeqCst);
                    let now = t0.elapsed().as_millis() as u64;
                    if s > 0 && now.saturating_sub(s) > hang.as_millis() as u64 {
                        eprintln!("fuzz {name}: a check ran past {} s (a hang); its input is {}", hang.as_secs(), current.display());
                        std::process::abort();
                    }
                    let own = rss_of("self").map_or(0, |r| r.0);
                    let pid = watched.load(Ordering::SeqCst);
                    let theirs = if pid > 0 { rss_of(&pid.to_string()).map_or(0, |r| r.0) } else { 0 };
                    peak_watched.fetch_max(theirs, Ordering::SeqCst);
                    if own > max_rss || theirs > max_rss {
                        eprintln!(
                            "fuzz {name}: resident memory {} MB (this process) / {} MB (server) is past the bound of {} MB; the last input is {}",
                            own >> 20,
                            theirs >> 20,
                            max_rss >> 20,
                            current.display()
                        );
                        std::process::abort();
                    }
                }
            })
        };
        let mut iterations = 0u64;
        // The corpus itself first (each must pass), then mutations.
        let mut queue: Vec<Vec<u8>> = self.corpus.clone();
        while self.budget.more(iterations, t0.elapsed()) || !queue.is_empty() || iterations < 20 {
            let input = match queue.pop() {
                Some(i) => i,
                None => {
                    let parent = self.corpus[self.rng.gen_range(0..self.corpus.len())].clone();
                    mutate(&mut self.rng, &parent, &self.corpus)
                }
            };
            let _ = std::fs::write(&self.current, &input);
            started_ms.store(t0.elapsed().as_millis().max(1) as u64, Ordering::SeqCst);
            let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| check(&input)));
            started_ms.store(0, Ordering::SeqCst);
            let class = match r {
                Ok(c) => c,
                Err(p) => {
                    stop.store(true, Ordering::SeqCst);
                    let why = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()));
                    let keep = self.dir.join(format!("crash-{:016x}", fnv(&input)));
                    let _ = std::fs::create_dir_all(&self.dir);
                    let _ = std::fs::write(&keep, &input);
                    let head = String::from_utf8_lossy(&input[..input.len().min(1500)]).into_owned();
                    panic!(
                        "fuzz {}: iteration {iterations} panicked ({}); input kept in {}; it starts:\n{head}",
                        self.name,
                        why.unwrap_or_default(),
                        keep.display()
                    );
                }
            };
            if self.classes.insert(class) && input.len() <= self.max_saved_len && self.corpus.len() < self.max_corpus {
                if self.save {
                    let _ = std::fs::create_dir_all(&self.dir);
                    let _ = std::fs::write(self.dir.join(format!("{:016x}", fnv(&input))), &input);
                }
                self.corpus.push(input);
            }
            iterations += 1;
        }
        stop.store(true, Ordering::SeqCst);
        let _ = dog.join();
        let _ = std::fs::remove_file(&self.current);
        let report = Report {
            iterations,
            seconds: t0.elapsed().as_secs_f64(),
            corpus: self.corpus.len(),
            classes: self.classes.len(),
            peak_rss: rss_of("self").map_or(0, |r| r.1),
            peak_watched_rss: peak_watched.load(Ordering::SeqCst),
        };
        eprintln!(
            "fuzz {}: {} inputs in {:.1} s ({:.0}/s), 0 panics, 0 hangs; {} outcome classes, corpus {}, peak memory {} MB (server {} MB)",
            self.name,
            report.iterations,
            report.seconds,
            report.iterations as f64 / report.seconds,
            report.classes,
            report.corpus,
            report.peak_rss >> 20,
            report.peak_watched_rss >> 20
        );
        if std::env::var("MSCALE_FUZZ_LOG").is_ok_and(|v| v == "1") {
            let line = format!(
                "| {} | {} | {:.0} | {} | {:.0} | 0 | 0 | {} | {} | {} | {} |\n",
                now_utc(),
                self.name,
                report.seconds,
                report.iterations,
                report.iterations as f64 / report.seconds,
                report.classes,
                report.corpus,
                report.peak_rss >> 20,
                report.peak_watched_rss >> 20
            );
            let log = self.dir.parent().map(|p| p.join("MEASUREMENTS.md")).unwrap_or_default();
            use std::io::Write;
            if let Ok(mut f) = std::fs::OpenOptions::new().create(true).append(true).open(&log) {
                let _ = f.write_all(line.as_bytes());
            }
        }
        report
    }
}

fn now_utc() -> String {
    std::process::Command::new("date")
        .args(["-u", "+%Y-%m-%d %H:%M"])
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_default()
}

/// One to three line-wise mutations of text: a token replaced by a hostile one, lines dropped,
/// doubled, swapped, a byte changed, a token dropped or added, truncation, a line spliced in
/// from another corpus input.
pub fn mutate_text(rng: &mut Rng64, parent: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    let text = String::from_utf8_lossy(parent);
    let mut lines: Vec<String> = text.lines().map(str::to_string).collect();
    for _ in 0..rng.gen_range(1..=3) {
        if lines.is_empty() {
            lines.push(String::new());
        }
        let n = lines.len();
        let at = rng.gen_range(0..n);
        match rng.gen_range(0..10) {
            0..=2 => {
                // A token (split at spaces and `=`) replaced by a hostile one.
                let line = lines[at].clone();
                let cuts: Vec<(usize, usize)> = token_spans(&line);
                let h = HOSTILE[rng.gen_range(0..HOSTILE.len())];
                lines[at] = if cuts.is_empty() {
                    h.to_string()
                } else {
                    let (a, b) = cuts[rng.gen_range(0..cuts.len())];
                    format!("{}{h}{}", &line[..a], &line[b..])
                };
            }
            3 => {
                lines.remove(at);
            }
            4 => {
                let l = lines[at].clone();
                lines.insert(at, l);
            }
            5 => {
                let b = rng.gen_range(0..n);
                lines.swap(at, b);
            }
            6 => {
                let mut w: Vec<&str> = lines[at].split_whitespace().collect();
                if !w.is_empty() && rng.gen_bool(0.5) {
                    w.remove(rng.gen_range(0..w.len()));
                } else {
                    w.push(HOSTILE[rng.gen_range(0..HOSTILE.len())]);
                }
                lines[at] = w.join(" ");
            }
            7 => {
                let mut b = lines[at].clone().into_bytes();
                if !b.is_empty() {
                    let k = rng.gen_range(0..b.len());
                    b[k] = rng.gen_range(32u8..127);
                }
                lines[at] = String::from_utf8_lossy(&b).into_owned();
            }
            8 => {
                // A line of another input.
                let other = String::from_utf8_lossy(&corpus[rng.gen_range(0..corpus.len())]).into_owned();
                let ol: Vec<&str> = other.lines().collect();
                if !ol.is_empty() {
                    lines.insert(at, ol[rng.gen_range(0..ol.len())].to_string());
                }
            }
            _ => {
                let keep = rng.gen_range(0..=lines[at].len());
                let mut cut = lines[at].clone();
                cut.truncate(cut.char_indices().map(|(i, _)| i).take_while(|&i| i <= keep).last().unwrap_or(0));
                lines.truncate(at);
                lines.push(cut);
            }
        }
    }
    (lines.join("\n") + "\n").into_bytes()
}

/// Byte ranges of the tokens of a line: runs between spaces, `=`, `,`, brackets and quotes.
fn token_spans(line: &str) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut start = None;
    for (i, c) in line.char_indices() {
        let sep = c.is_whitespace() || matches!(c, '=' | ',' | '[' | ']' | '{' | '}');
        match (sep, start) {
            (true, Some(s)) => {
                out.push((s, i));
                start = None;
            }
            (false, None) => start = Some(i),
            _ => {}
        }
    }
    if let Some(s) = start {
        out.push((s, line.len()));
    }
    out
}

/// A protobuf varint.
pub fn varint(mut v: u64, out: &mut Vec<u8>) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Hostile 64-bit values for varint and fixed64 fields.
pub fn hostile_u64(rng: &mut Rng64) -> u64 {
    const V: &[u64] = &[0, 1, 2, 3, 7, 255, 65535, 1 << 31, u32::MAX as u64, 1 << 32, i64::MAX as u64, u64::MAX, u64::MAX - 1];
    if rng.gen_bool(0.7) { V[rng.gen_range(0..V.len())] } else { rng.r#gen() }
}

/// Hostile doubles (as bits) for fixed64 fields.
pub fn hostile_f64(rng: &mut Rng64) -> f64 {
    const V: &[f64] = &[0.0, -0.0, 1.0, -1.0, 1e308, -1e308, f64::MAX, f64::MIN_POSITIVE, 5e-324, 1e30, -1e30, 1e6, 3.615];
    match rng.gen_range(0..4) {
        0 => f64::NAN,
        1 => {
            if rng.gen_bool(0.5) {
                f64::INFINITY
            } else {
                f64::NEG_INFINITY
            }
        }
        _ => V[rng.gen_range(0..V.len())],
    }
}

/// One to four byte-level mutations of a binary message: bits flipped, bytes set to edge
/// values, ranges deleted, duplicated or spliced from another input, truncation, and
/// protobuf-aware ones: a field of a random number and wire type with a hostile value
/// appended or inserted, a length prefix rewritten.
pub fn mutate_bytes(rng: &mut Rng64, parent: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    let mut b = parent.to_vec();
    for _ in 0..rng.gen_range(1..=4) {
        let n = b.len();
        match rng.gen_range(0..11) {
            0 if n > 0 => {
                let k = rng.gen_range(0..n);
                b[k] ^= 1 << rng.gen_range(0..8);
            }
            1 if n > 0 => {
                let k = rng.gen_range(0..n);
                b[k] = [0u8, 0xff, 0x7f, 0x80, 0x01][rng.gen_range(0..5)];
            }
            2 if n > 0 => {
                let a = rng.gen_range(0..n);
                let e = (a + rng.gen_range(1..=16)).min(n);
                b.drain(a..e);
            }
            3 if n > 0 => {
                let a = rng.gen_range(0..n);
                let e = (a + rng.gen_range(1..=32)).min(n);
                let piece = b[a..e].to_vec();
                let at = rng.gen_range(0..=b.len());
                b.splice(at..at, piece);
            }
            4 => {
                let other = &corpus[rng.gen_range(0..corpus.len())];
                if !other.is_empty() {
                    let a = rng.gen_range(0..other.len());
                    let e = (a + rng.gen_range(1..=64)).min(other.len());
                    let at = rng.gen_range(0..=b.len());
                    b.splice(at..at, other[a..e].iter().copied());
                }
            }
            5 if n > 0 => {
                b.truncate(rng.gen_range(0..n));
            }
            6..=8 => {
                // A field with a hostile value, at the end (a field of the outer message) or
                // anywhere (often inside a nested one, or breaking it).
                let field: u64 = if rng.gen_bool(0.8) { rng.gen_range(1..16) } else { rng.gen_range(1..1 << 29) };
                // Mostly the four wire types of proto3, sometimes the group ones.
                let kinds = if rng.gen_bool(0.9) { 4 } else { 6 };
                let wire = [0u64, 1, 2, 5, 3, 4][rng.gen_range(0..kinds)];
                let mut f = Vec::new();
                varint(field << 3 | wire, &mut f);
                match wire {
                    0 => varint(hostile_u64(rng), &mut f),
                    1 => f.extend_from_slice(&hostile_f64(rng).to_bits().to_le_bytes()),
                    2 => {
                        let len = rng.gen_range(0..48usize);
                        if rng.gen_bool(0.15) {
                            // A length past the message.
                            varint(hostile_u64(rng), &mut f);
                        } else {
                            varint(len as u64, &mut f);
                        }
                        for _ in 0..len {
                            let v =
                                if rng.gen_bool(0.5) { hostile_f64(rng).to_bits().to_le_bytes()[rng.gen_range(0..8)] } else { rng.r#gen() };
                            f.push(v);
                        }
                    }
                    5 => f.extend_from_slice(&(hostile_u64(rng) as u32).to_le_bytes()),
                    _ => {}
                }
                let at = if rng.gen_bool(0.5) { b.len() } else { rng.gen_range(0..=b.len()) };
                b.splice(at..at, f);
            }
            9 if n > 8 => {
                // An 8-byte run (a double of a packed field, often) set to a hostile double.
                let k = rng.gen_range(0..n - 8);
                b[k..k + 8].copy_from_slice(&hostile_f64(rng).to_bits().to_le_bytes());
            }
            _ => {
                let at = rng.gen_range(0..=b.len());
                b.insert(at, rng.r#gen());
            }
        }
    }
    b
}

/// A random change somewhere in a JSON value: a number made hostile, an array cut, emptied,
/// grown or with an element doubled, a string changed, a key removed, a value of another type.
pub fn mutate_json(rng: &mut Rng64, v: &mut serde_json::Value) {
    use serde_json::Value;
    // Pick a node by a random walk from the root.
    let mut node = v;
    loop {
        let go_down = rng.gen_bool(0.8);
        let next_len = match &*node {
            Value::Array(a) => a.len(),
            Value::Object(o) => o.len(),
            _ => 0,
        };
        if !go_down || next_len == 0 {
            break;
        }
        let k = rng.gen_range(0..next_len);
        node = match node {
            Value::Array(a) => &mut a[k],
            Value::Object(o) => o.values_mut().nth(k).expect("in range"),
            _ => unreachable!(),
        };
    }
    let hostile_number = |rng: &mut Rng64| -> Value {
        match rng.gen_range(0..8) {
            0 => Value::from(-1),
            1 => Value::from(u64::MAX),
            2 => Value::from(1e308),
            3 => Value::from(-1e308),
            4 => Value::from(0),
            5 => Value::from(i64::MIN),
            6 => Value::from(4294967296u64),
            _ => Value::from(5e-324),
        }
    };
    match node {
        Value::Number(_) => *node = hostile_number(rng),
        Value::Array(a) => match rng.gen_range(0..5) {
            0 => a.clear(),
            1 => {
                let n = a.len();
                a.truncate(rng.gen_range(0..=n));
            }
            2 if !a.is_empty() => {
                let k = rng.gen_range(0..a.len());
                let x = a[k].clone();
                a.insert(k, x);
            }
            3 => a.push(hostile_number(rng)),
            _ => *node = Value::Null,
        },
        Value::Object(o) => {
            if !o.is_empty() && rng.gen_bool(0.6) {
                let k = o.keys().nth(rng.gen_range(0..o.len())).cloned().expect("in range");
                o.remove(&k);
            } else {
                o.insert("unknown".into(), hostile_number(rng));
            }
        }
        Value::String(s) => {
            *s = ["", "x", "cell", "\u{fffd}", "../..", "0"][rng.gen_range(0..6)].to_string();
        }
        Value::Bool(b) => *b = !*b,
        Value::Null => *node = hostile_number(rng),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn threads_of_names_each_thread_and_its_state() {
        let t = std::thread::Builder::new().name("parked-one".into()).spawn(std::thread::park).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(50));
        let s = super::threads_of(std::process::id());
        assert!(s.contains("\"parked-one\" S (sleeping)"), "{s}");
        // With gdb installed, the parked thread's frame in this test is named.
        if std::process::Command::new("gdb").arg("--version").output().is_ok() {
            assert!(s.contains("testkit/src/fuzz.rs"), "{s}");
        }
        t.thread().unpark();
        t.join().unwrap();
        assert!(super::threads_of(u32::MAX).contains("no /proc"));
    }
}
