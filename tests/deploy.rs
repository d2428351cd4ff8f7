//! Static checks of the deployment files in deploy/ (Slurm, Kubernetes, systemd, Docker).
//! The Slurm scripts also run for real, under the single-node cluster of `deploy/setup.sh
//! slurm`, in tests/slurm.rs. Nothing here can run Kubernetes, systemd or a Docker engine, so
//! the files are parsed and
//! every binary, subcommand, flag, port and repository path they name is checked against the
//! real thing: flags come from the `--help` of the binaries built from this tree, paths from
//! the repository, ports are compared across files. Where a tool is installed
//! (`systemd-analyze`, `kubectl`), it checks its files too; `bash -n` checks every script.
//! One check runs for real: the orchestrator command and health probe of the Kubernetes
//! Deployment, with certificates from deploy/make-certs.sh, on this machine.

use mscale_tests::{binary, repo};
use regex::Regex;
use serde_yaml::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

// ---------------------------------------------------------------- the binaries' interfaces

/// One level of a program's command line, from its `--help`.
#[derive(Debug, Default)]
struct Level {
    /// Long flag name (without `--`) -> takes a value.
    long: BTreeMap<String, bool>,
    /// Short flag letter -> takes a value.
    short: BTreeMap<char, bool>,
    subcommands: BTreeMap<String, Level>,
    /// The `--help` text (for defaults).
    help: String,
}

fn help_text(bin: &Path, path: &[&str]) -> String {
    let o = Command::new(bin).args(path).arg("--help").output().unwrap_or_else(|e| panic!("{} {path:?} --help: {e}", bin.display()));
    assert!(o.status.success(), "{} {path:?} --help failed: {}", bin.display(), String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Flags and subcommands of clap's help output.
fn parse_level(bin: &Path, path: &[&str]) -> Level {
    let help = help_text(bin, path);
    let flag = Regex::new(r"^(?: {2}-([A-Za-z0-9]), | {2,6})--([a-z0-9][a-z0-9-]*)(?:[ =](\[?<))?").expect("regex");
    let short_only = Regex::new(r"^ {2}-([A-Za-z0-9])(?:[ ,]|$)( <)?").expect("regex");
    let alias = Regex::new(r"\[alias(?:es)?: ([^\]]+)\]").expect("regex");
    let sub = Regex::new(r"^ {2}([a-z][a-z0-9-]*)(?: {2,}|$)").expect("regex");
    let mut level = Level { help: help.clone(), ..Level::default() };
    let mut section = "";
    for line in help.lines() {
        if !line.starts_with(' ') && line.ends_with(':') {
            section = line.trim_end_matches(':');
            continue;
        }
        match section {
            "Commands" => {
                if let Some(c) = sub.captures(line) {
                    let name = c[1].to_string();
                    if name != "help" {
                        let mut p = path.to_vec();
                        p.push(&name);
                        level.subcommands.insert(name.clone(), parse_level(bin, &p));
                    }
                }
            }
            "Options" => {
                if let Some(c) = flag.captures(line) {
                    let takes = c.get(3).is_some();
                    level.long.insert(c[2].to_string(), takes);
                    if let Some(s) = c.get(1) {
                        level.short.insert(s.as_str().chars().next().unwrap_or('?'), takes);
                    }
                    if let Some(a) = alias.captures(line) {
                        for name in a[1].split(',') {
                            level.long.insert(name.trim().trim_start_matches("--").to_string(), takes);
                        }
                    }
                } else if let Some(c) = short_only.captures(line) {
                    level.short.insert(c[1].chars().next().unwrap_or('?'), c.get(2).is_some());
                } else if let Some(a) = alias.captures(line) {
                    // In long help the alias stands on a line of its own, under its flag.
                    for name in a[1].split(',') {
                        level.long.entry(name.trim().trim_start_matches("--").to_string()).or_insert(true);
                    }
                }
            }
            _ => {}
        }
    }
    level
}

const PROGRAMS: [(&str, &str); 2] = [("mscale", "orchestrator"), ("md-worker", "md-worker")];

/// The command lines of `mscale` and `md-worker` as built from this tree.
fn programs() -> &'static BTreeMap<String, Level> {
    static P: OnceLock<BTreeMap<String, Level>> = OnceLock::new();
    P.get_or_init(|| PROGRAMS.iter().map(|(name, package)| (name.to_string(), parse_level(&binary(name, package), &[]))).collect())
}

// ---------------------------------------------------------------- shell words

/// Splits shell text into words and control operators (`;`, `&`, `&&`, `|`, `||`, `(`, `)`,
/// newlines as `;`). Quotes are removed; redirections are dropped with their targets.
/// Expands `$VAR` and `${VAR}` where `vars` knows VAR.
fn shell_words(text: &str, vars: &BTreeMap<String, String>) -> Vec<String> {
    let text = text.replace("\\\n", " ");
    let chars: Vec<char> = text.chars().collect();
    let mut out = Vec::new();
    let mut word = String::new();
    let mut in_word = false;
    let mut i = 0;
    let flush = |word: &mut String, in_word: &mut bool, out: &mut Vec<String>| {
        if *in_word {
            out.push(expand(word, vars));
            word.clear();
            *in_word = false;
        }
    };
    while i < chars.len() {
        let c = chars[i];
        match c {
            '\'' => {
                in_word = true;
                i += 1;
                while i < chars.len() && chars[i] != '\'' {
                    // Protect single-quoted text from expansion.
                    if chars[i] == '$' {
                        word.push('\u{0}');
                    } else {
                        word.push(chars[i]);
                    }
                    i += 1;
                }
            }
            '"' => {
                in_word = true;
                i += 1;
                while i < chars.len() && chars[i] != '"' {
                    if chars[i] == '\\' && i + 1 < chars.len() {
                        i += 1;
                    }
                    word.push(chars[i]);
                    i += 1;
                }
            }
            '\\' if i + 1 < chars.len() => {
                in_word = true;
                word.push(chars[i + 1]);
                i += 1;
            }
            '#' if !in_word => {
                while i < chars.len() && chars[i] != '\n' {
                    i += 1;
                }
                continue;
            }
            ' ' | '\t' => flush(&mut word, &mut in_word, &mut out),
            '\n' | ';' => {
                flush(&mut word, &mut in_word, &mut out);
                out.push(";".into());
            }
            '&' | '|' | '(' | ')' => {
                if c == '(' && word.ends_with('$') {
                    // $( ... ): the command inside starts a new command.
                    word.pop();
                    if word.is_empty() {
                        in_word = false;
                    }
                }
                flush(&mut word, &mut in_word, &mut out);
                if (c == '&' || c == '|') && chars.get(i + 1) == Some(&c) {
                    i += 1;
                    out.push(format!("{c}{c}"));
                } else {
                    out.push(c.to_string());
                }
            }
            '>' | '<' => {
                if word.chars().all(|d| d.is_ascii_digit()) {
                    word.clear();
                    in_word = false;
                }
                flush(&mut word, &mut in_word, &mut out);
                if c == '<' && chars.get(i + 1) == Some(&'(') {
                    i += 1;
                    continue; // process substitution: `(` is handled next round
                }
                while i + 1 < chars.len() && matches!(chars[i + 1], '>' | '<' | '&') {
                    i += 1;
                }
                while i + 1 < chars.len() && chars[i + 1] == ' ' {
                    i += 1;
                }
                // The target word.
                if chars.get(i + 1) == Some(&'(') {
                    // `< <(cmd)`: the next round handles `<(`
                } else {
                    while i + 1 < chars.len() && !matches!(chars[i + 1], ' ' | '\t' | '\n' | ';' | '&' | '|' | ')') {
                        i += 1;
                    }
                }
            }
            _ => {
                in_word = true;
                word.push(c);
            }
        }
        i += 1;
    }
    flush(&mut word, &mut in_word, &mut out);
    out.into_iter().map(|w| w.replace('\u{0}', "$")).collect()
}

fn expand(word: &str, vars: &BTreeMap<String, String>) -> String {
    let re = Regex::new(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}|\$([A-Za-z_][A-Za-z0-9_]*)").expect("regex");
    re.replace_all(word, |c: &regex::Captures| {
        let name = c.get(1).or(c.get(2)).map(|m| m.as_str()).unwrap_or("");
        vars.get(name).cloned().unwrap_or_else(|| c[0].to_string())
    })
    .into_owned()
}

fn is_separator(w: &str) -> bool {
    matches!(w, ";" | "&" | "&&" | "|" | "||" | "(" | ")")
}

/// Words that may stand before a command without being it.
fn is_prefix_word(w: &str) -> bool {
    matches!(w, "if" | "then" | "else" | "elif" | "do" | "while" | "until" | "!" | "time" | "{" | "}")
        || Regex::new(r"^[A-Za-z_][A-Za-z0-9_]*=").expect("regex").is_match(w)
}

/// Commands that run another program given after their own options.
const WRAPPERS: [&str; 6] = ["srun", "mpirun", "mpiexec", "exec", "env", "nice"];

fn basename(w: &str) -> &str {
    w.rsplit('/').next().unwrap_or(w)
}

// ---------------------------------------------------------------- invocations

/// One run of `mscale` or `md-worker` named in a deployment file.
#[derive(Debug, Clone)]
struct Invocation {
    origin: String,
    program: String,
    /// Subcommand path, e.g. ["serve"].
    command: Vec<String>,
    flags: Vec<(String, Option<String>)>,
    positionals: Vec<String>,
    /// Options of the wrapper it runs under (srun, mpirun), e.g. ["--mpi=pmix"].
    wrapper: Option<(String, Vec<String>)>,
}

impl Invocation {
    fn flag(&self, name: &str) -> Option<&str> {
        self.flags.iter().find(|(n, _)| n == name).and_then(|(_, v)| v.as_deref())
    }
    fn is(&self, program: &str, command: &str) -> bool {
        self.program == program && self.command.join(" ") == command
    }
}

/// Finds the invocations of the programs in words (one command list: shell text, an exec
/// array, an ExecStart line) and checks each against the program's help. Errors go to `errors`.
fn invocations(words: &[String], origin: &str, errors: &mut Vec<String>) -> Vec<Invocation> {
    let programs = programs();
    let mut found = Vec::new();
    let mut i = 0;
    let mut at_command = true;
    while i < words.len() {
        let w = &words[i];
        if is_separator(w) {
            at_command = true;
            i += 1;
            continue;
        }
        if !at_command {
            i += 1;
            continue;
        }
        if is_prefix_word(w) {
            i += 1;
            continue;
        }
        at_command = false;
        let mut wrapper = None;
        let mut p = i;
        if WRAPPERS.contains(&basename(w)) {
            // Skip the wrapper's options up to the program it runs.
            let mut opts = Vec::new();
            let mut j = i + 1;
            while j < words.len() && !is_separator(&words[j]) && !programs.contains_key(basename(&words[j])) {
                opts.push(words[j].clone());
                j += 1;
            }
            if j >= words.len() || is_separator(&words[j]) {
                i = j;
                continue;
            }
            wrapper = Some((basename(w).to_string(), opts));
            p = j;
        }
        let name = basename(&words[p]).to_string();
        let Some(top) = programs.get(&name) else {
            i = p + 1;
            continue;
        };
        let mut inv = Invocation {
            origin: origin.to_string(),
            program: name.clone(),
            command: Vec::new(),
            flags: Vec::new(),
            positionals: Vec::new(),
            wrapper,
        };
        let mut level = top;
        let mut j = p + 1;
        // Subcommand path.
        while j < words.len() && !is_separator(&words[j]) && !words[j].starts_with('-') {
            match level.subcommands.get(&words[j]) {
                Some(l) => {
                    inv.command.push(words[j].clone());
                    level = l;
                    j += 1;
                }
                None if level.subcommands.is_empty() => break,
                None => {
                    errors.push(format!(
                        "{origin}: `{name} {}` is not a subcommand of `{name}{}` (it has: {})",
                        words[j],
                        inv.command.iter().map(|c| format!(" {c}")).collect::<String>(),
                        level.subcommands.keys().cloned().collect::<Vec<_>>().join(", ")
                    ));
                    break;
                }
            }
        }
        if inv.command.is_empty()
            && !top.subcommands.is_empty()
            && !(j < words.len() && matches!(words[j].as_str(), "--help" | "-h" | "--version" | "-V"))
        {
            errors.push(format!("{origin}: `{name}` without a subcommand"));
        }
        let what = format!("{name}{}", inv.command.iter().map(|c| format!(" {c}")).collect::<String>());
        while j < words.len() && !is_separator(&words[j]) {
            let w = &words[j];
            if let Some(long) = w.strip_prefix("--") {
                let (flag, inline) = match long.split_once('=') {
                    Some((f, v)) => (f.to_string(), Some(v.to_string())),
                    None => (long.to_string(), None),
                };
                match level.long.get(&flag) {
                    None => {
                        errors.push(format!(
                            "{origin}: `{what}` has no flag --{flag} (its flags: {})",
                            level.long.keys().map(|k| format!("--{k}")).collect::<Vec<_>>().join(" ")
                        ));
                        // Keep its value (a guess) so that later checks do not fail on its absence.
                        let value = inline
                            .or_else(|| words.get(j + 1).filter(|v| !is_separator(v) && !v.starts_with('-')).inspect(|_| j += 1).cloned());
                        inv.flags.push((flag, value));
                    }
                    Some(&takes) => {
                        let value = if takes && inline.is_none() {
                            j += 1;
                            match words.get(j).filter(|v| !is_separator(v)) {
                                Some(v) => Some(v.clone()),
                                None => {
                                    errors.push(format!("{origin}: `{what} --{flag}` needs a value"));
                                    None
                                }
                            }
                        } else {
                            if !takes && inline.is_some() {
                                errors.push(format!("{origin}: `{what} --{flag}` takes no value"));
                            }
                            inline
                        };
                        inv.flags.push((flag, value));
                    }
                }
            } else if w.len() > 1 && w.starts_with('-') && !w.starts_with("--") {
                let c = w.chars().nth(1).unwrap_or('?');
                match level.short.get(&c) {
                    None => errors.push(format!("{origin}: `{what}` has no flag -{c}")),
                    Some(&true) => j += 1,
                    Some(&false) => {}
                }
            } else {
                inv.positionals.push(w.clone());
            }
            j += 1;
        }
        found.push(inv);
        i = j;
    }
    found
}

// ---------------------------------------------------------------- the files

fn deploy() -> PathBuf {
    repo().join("deploy")
}

fn read(p: &Path) -> String {
    std::fs::read_to_string(p).unwrap_or_else(|e| panic!("cannot read {}: {e}", p.display()))
}

fn files(dir: &str, suffixes: &[&str]) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(deploy().join(dir))
        .unwrap_or_else(|e| panic!("deploy/{dir}: {e}"))
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| suffixes.iter().any(|s| p.to_string_lossy().ends_with(s)))
        .collect();
    v.sort();
    assert!(!v.is_empty(), "no {suffixes:?} files in deploy/{dir}");
    v
}

fn rel(p: &Path) -> String {
    p.strip_prefix(repo()).unwrap_or(p).to_string_lossy().trim_start_matches("../").to_string()
}

fn report(what: &str, errors: Vec<String>) {
    assert!(errors.is_empty(), "{what}: {} problem(s):\n  {}", errors.len(), errors.join("\n  "));
}

/// Values of a script's top-level variables as far as they are literal: `VAR="${VAR:-default}"`
/// gives the default, `VAR="text"` the text with earlier variables expanded.
fn script_defaults(text: &str) -> BTreeMap<String, String> {
    let default = Regex::new(r#"^([A-Za-z_][A-Za-z0-9_]*)="\$\{([A-Za-z_][A-Za-z0-9_]*):-([^}$]*)\}"\s*$"#).expect("regex");
    let plain = Regex::new(r#"^([A-Za-z_][A-Za-z0-9_]*)="([^"`]*)"\s*$"#).expect("regex");
    let mut vars = BTreeMap::new();
    for line in text.lines() {
        if let Some(c) = default.captures(line) {
            if c[1] == c[2] {
                vars.insert(c[1].to_string(), c[3].to_string());
            }
        } else if let Some(c) = plain.captures(line).filter(|c| !c[2].contains("$(") && !c[2].contains("${")) {
            let v = expand(&c[2], &vars);
            vars.insert(c[1].to_string(), v);
        }
    }
    vars
}

/// Every invocation in the Slurm scripts, with `bash -n` and #SBATCH/srun checks.
fn slurm(errors: &mut Vec<String>) -> Vec<Invocation> {
    const SBATCH: &[&str] = &[
        "job-name",
        "nodes",
        "ntasks",
        "ntasks-per-node",
        "gpus-per-node",
        "gpus-per-task",
        "gpus",
        "gres",
        "cpus-per-task",
        "mem",
        "mem-per-cpu",
        "time",
        "output",
        "error",
        "exclusive",
        "partition",
        "account",
        "qos",
        "constraint",
        "signal",
        "requeue",
    ];
    const SRUN: &[&str] = &[
        "nodes",
        "ntasks",
        "ntasks-per-node",
        "nodelist",
        "gres",
        "overlap",
        "exact",
        "kill-on-bad-exit",
        "gpus-per-task",
        "gpus",
        "mpi",
        "cpus-per-task",
        "mem",
        "label",
        "export",
        "output",
        "error",
        "cpu-bind",
        "gpu-bind",
        "job-name",
    ];
    let mut all = Vec::new();
    for p in files("slurm", &[".sbatch", ".sh"]) {
        let text = read(&p);
        let name = rel(&p);
        bash_n(&p, errors);
        if !text.starts_with("#!/usr/bin/env bash\n") && !text.starts_with("#!/bin/bash\n") {
            errors.push(format!("{name}: does not start with a bash shebang"));
        }
        if name.ends_with(".sbatch") {
            let mut directives = 0;
            for line in text.lines().filter(|l| l.starts_with("#SBATCH")) {
                directives += 1;
                match line.strip_prefix("#SBATCH --").and_then(|o| o.split(['=', ' ']).next()) {
                    Some(o) if SBATCH.contains(&o) => {}
                    _ => errors.push(format!("{name}: unknown or malformed directive `{line}`")),
                }
            }
            if directives == 0 {
                errors.push(format!("{name}: no #SBATCH directives"));
            }
        }
        let vars = script_defaults(&text);
        let words = shell_words(&text, &vars);
        let found = invocations(&words, &name, errors);
        for inv in &found {
            if let Some((_, opts)) = inv.wrapper.as_ref().filter(|(w, _)| w == "srun") {
                for o in opts.iter().filter_map(|o| o.strip_prefix("--")) {
                    let o = o.split('=').next().unwrap_or(o);
                    if !SRUN.contains(&o) {
                        errors.push(format!("{name}: srun option --{o} is not one srun has (or not in this test's list)"));
                    }
                }
            }
        }
        all.extend(found);
    }
    all
}

fn bash_n(p: &Path, errors: &mut Vec<String>) {
    let o = Command::new("bash").arg("-n").arg(p).output().expect("run bash -n");
    if !o.status.success() {
        errors.push(format!("bash -n {}: {}", rel(p), String::from_utf8_lossy(&o.stderr)));
    }
}

/// A systemd unit: (section, key, value) in order.
fn unit_entries(text: &str, name: &str, errors: &mut Vec<String>) -> Vec<(String, String, String)> {
    let mut out = Vec::new();
    let mut section = String::new();
    let text = text.replace("\\\n", " ");
    let key = Regex::new(r"^[A-Za-z][A-Za-z0-9]*$").expect("regex");
    for (n, line) in text.lines().enumerate() {
        let t = line.trim();
        if t.is_empty() || t.starts_with('#') || t.starts_with(';') {
            continue;
        }
        if t.starts_with('[') {
            if !t.ends_with(']') {
                errors.push(format!("{name}:{}: bad section header {t:?}", n + 1));
            }
            section = t.trim_matches(['[', ']']).to_string();
            if !["Unit", "Service", "Install"].contains(&section.as_str()) {
                errors.push(format!("{name}:{}: unexpected section [{section}]", n + 1));
            }
            continue;
        }
        match t.split_once('=') {
            Some((k, v)) if !section.is_empty() && key.is_match(k.trim()) => {
                out.push((section.clone(), k.trim().to_string(), v.trim().to_string()))
            }
            _ => errors.push(format!("{name}:{}: not `Key=Value` in a section: {t:?}", n + 1)),
        }
    }
    out
}

/// Every invocation in the systemd units, with the units' own checks.
fn systemd(errors: &mut Vec<String>) -> Vec<Invocation> {
    let mut all = Vec::new();
    let units = files("systemd", &[".service"]);
    let (env_use, credential) = (Regex::new(r"\$\{([A-Za-z_0-9]+)\}").expect("regex"), Regex::new(r"%d/([A-Za-z0-9_.-]+)").expect("regex"));
    for p in &units {
        let name = rel(p);
        let file = p.file_name().map(|f| f.to_string_lossy().to_string()).unwrap_or_default();
        let text = read(p);
        let entries = unit_entries(&text, &name, errors);
        let get = |s: &str, k: &str| entries.iter().filter(|(es, ek, _)| es == s && ek == k).map(|(_, _, v)| v.clone()).collect::<Vec<_>>();
        for s in ["Unit", "Service", "Install"] {
            if !entries.iter().any(|(es, _, _)| es == s) {
                errors.push(format!("{name}: no [{s}] section"));
            }
        }
        let template = file.contains("@.");
        if template != text.contains("%i") {
            errors.push(format!("{name}: a template unit (NAME@.service) and the use of %i go together"));
        }
        // Environment= defaults, for ${VAR} in ExecStart.
        let mut env = BTreeMap::new();
        for v in get("Service", "Environment") {
            for w in shell_words(&v, &BTreeMap::new()) {
                if let Some((k, v)) = w.split_once('=') {
                    env.insert(k.to_string(), v.to_string());
                }
            }
        }
        let creds: BTreeSet<String> =
            get("Service", "LoadCredential").iter().filter_map(|v| v.split(':').next().map(String::from)).collect();
        let exec = get("Service", "ExecStart");
        if exec.len() != 1 {
            errors.push(format!("{name}: expected one ExecStart=, found {}", exec.len()));
        }
        for line in exec {
            let line = line.trim_start_matches(['-', '@', '+', '!', ':']);
            for var in env_use.captures_iter(line) {
                if !env.contains_key(&var[1]) {
                    errors.push(format!("{name}: ExecStart uses ${{{}}}, which no Environment= sets", &var[1]));
                }
            }
            for c in credential.captures_iter(line) {
                if !creds.contains(&c[1]) {
                    errors.push(format!("{name}: ExecStart reads credential {} that no LoadCredential= loads", &c[1]));
                }
            }
            let words = shell_words(line, &env);
            if !words.first().is_some_and(|w| w.starts_with('/') && programs().contains_key(basename(w))) {
                errors.push(format!("{name}: ExecStart does not start with the absolute path of mscale or md-worker: {line}"));
            }
            all.extend(invocations(&words, &name, errors));
        }
    }
    systemd_analyze(&units, errors);
    all
}

/// `systemd-analyze verify` (where installed) on copies of the units whose binaries point at
/// the ones built here: unknown keys, bad values and specifiers are reported.
fn systemd_analyze(units: &[PathBuf], errors: &mut Vec<String>) {
    if Command::new("systemd-analyze").arg("--version").output().is_err() {
        eprintln!("deploy: systemd-analyze is not installed; the units get the parser's checks only");
        return;
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut args = vec!["verify".to_string()];
    for p in units {
        let mut text = read(p);
        for (bin, package) in PROGRAMS {
            text = text.replace(&format!("/usr/local/bin/{bin} "), &format!("{} ", binary(bin, package).display()));
        }
        let file = p.file_name().map(|f| f.to_string_lossy().replace("@.", "@0.")).unwrap_or_default();
        std::fs::write(tmp.path().join(&file), text).expect("write unit copy");
        args.push(format!("./{file}"));
    }
    let o = Command::new("systemd-analyze").args(&args).current_dir(tmp.path()).output().expect("systemd-analyze");
    let msg = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    // Users and credential files of the target host do not exist here; those are not errors.
    let msg: Vec<&str> =
        msg.lines().filter(|l| !l.trim().is_empty() && !l.contains("/etc/mscale") && !l.contains("User") && !l.contains("Group")).collect();
    if !o.status.success() || !msg.is_empty() {
        errors.push(format!("systemd-analyze verify: {}", msg.join(" | ")));
    }
}

/// All documents of the YAML files in deploy/k8s, with their file names.
fn k8s_docs() -> Vec<(String, Value)> {
    let mut docs = Vec::new();
    for p in files("k8s", &[".yaml", ".yml"]) {
        let text = read(&p);
        for d in serde_yaml::Deserializer::from_str(&text) {
            let v = Value::deserialize(d).unwrap_or_else(|e| panic!("{}: not YAML: {e}", rel(&p)));
            if !v.is_null() {
                docs.push((rel(&p), v));
            }
        }
    }
    docs
}

use serde::Deserialize;

fn s<'a>(v: &'a Value, path: &[&str]) -> Option<&'a Value> {
    path.iter().try_fold(v, |v, k| v.get(*k))
}

fn st(v: &Value, path: &[&str]) -> String {
    match s(v, path) {
        Some(Value::String(x)) => x.clone(),
        Some(Value::Number(n)) => n.to_string(),
        _ => String::new(),
    }
}

fn seq(v: Option<&Value>) -> Vec<Value> {
    v.and_then(|v| v.as_sequence()).cloned().unwrap_or_default()
}

fn words_of(v: Option<&Value>) -> Vec<String> {
    seq(v)
        .iter()
        .map(|w| match w {
            Value::String(s) => s.clone(),
            other => serde_yaml::to_string(other).unwrap_or_default().trim().to_string(),
        })
        .collect()
}

/// A workload's containers with where they come from.
struct Container {
    origin: String,
    workload: Value,
    container: Value,
}

fn containers(docs: &[(String, Value)]) -> Vec<Container> {
    let mut out = Vec::new();
    for (file, d) in docs {
        for c in seq(s(d, &["spec", "template", "spec", "containers"])) {
            out.push(Container {
                origin: format!("{file}: {} {}/{}", st(d, &["kind"]), st(d, &["metadata", "name"]), st(&c, &["name"])),
                workload: d.clone(),
                container: c,
            });
        }
    }
    out
}

/// Every invocation in the Kubernetes manifests (containers' command + args, exec probes).
fn k8s(errors: &mut Vec<String>) -> Vec<Invocation> {
    let docs = k8s_docs();
    let mut all = Vec::new();
    for c in containers(&docs) {
        let mut words = words_of(c.container.get("command"));
        words.extend(words_of(c.container.get("args")));
        if !words.first().is_some_and(|w| programs().contains_key(basename(w))) {
            errors.push(format!("{}: the container runs {:?}, not mscale or md-worker", c.origin, words.first()));
        }
        all.extend(invocations(&words, &c.origin, errors));
        for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
            let w = words_of(s(&c.container, &[probe, "exec", "command"]));
            if !w.is_empty() {
                all.extend(invocations(&w, &format!("{} {probe}", c.origin), errors));
            }
        }
    }
    all
}

// ---------------------------------------------------------------- the Dockerfile

struct Instruction {
    line: usize,
    keyword: String,
    rest: String,
    stage: usize,
}

fn dockerfile() -> (Vec<Instruction>, Vec<(String, Vec<String>)>) {
    let text = read(&deploy().join("Dockerfile"));
    let mut out = Vec::new();
    // Stages: (name, ARGs declared in the stage).
    let mut stages: Vec<(String, Vec<String>)> = Vec::new();
    let mut joined = String::new();
    let mut start = 0;
    for (n, line) in text.lines().enumerate() {
        if joined.is_empty() {
            start = n + 1;
            if line.trim_start().starts_with('#') || line.trim().is_empty() {
                continue;
            }
        } else if line.trim_start().starts_with('#') {
            continue; // comments inside a continued instruction
        }
        if let Some(l) = line.strip_suffix('\\') {
            joined.push_str(l);
            joined.push(' ');
            continue;
        }
        joined.push_str(line);
        let (k, rest) = joined
            .trim()
            .split_once(char::is_whitespace)
            .map(|(k, r)| (k.to_uppercase(), r.trim().to_string()))
            .unwrap_or((joined.trim().to_uppercase(), String::new()));
        if k == "FROM" {
            let name = rest.split_whitespace().collect::<Vec<_>>();
            let alias = match name.as_slice() {
                [_, as_, n] if as_.eq_ignore_ascii_case("as") => n.to_string(),
                _ => String::new(),
            };
            stages.push((alias, Vec::new()));
        }
        if k == "ARG" {
            let arg = rest.split('=').next().unwrap_or("").trim().to_string();
            match stages.last_mut() {
                Some(s) => s.1.push(arg),
                None => out.push(Instruction { line: start, keyword: "GLOBAL-ARG".into(), rest: arg, stage: 0 }),
            }
        }
        out.push(Instruction { line: start, keyword: k, rest, stage: stages.len() });
        joined.clear();
    }
    (out, stages)
}

/// (source in the repository, destination in the image) of the runtime stage's COPY lines.
fn image_copies() -> Vec<(String, String)> {
    let (ins, stages) = dockerfile();
    ins.iter()
        .filter(|i| i.keyword == "COPY" && i.stage == stages.len() && !i.rest.contains("--from"))
        .filter_map(|i| {
            let w: Vec<&str> = i.rest.split_whitespace().filter(|w| !w.starts_with("--")).collect();
            (w.len() == 2).then(|| (w[0].to_string(), w[1].trim_end_matches('/').to_string()))
        })
        .collect()
}

/// Ports the image declares.
fn exposed() -> BTreeSet<u16> {
    dockerfile()
        .0
        .iter()
        .filter(|i| i.keyword == "EXPOSE")
        .flat_map(|i| i.rest.split_whitespace().filter_map(|p| p.split('/').next()?.parse().ok()).collect::<Vec<_>>())
        .collect()
}

fn cargo_toml(p: &str) -> toml::Value {
    read(&repo().join(p)).parse().unwrap_or_else(|e| panic!("{p}: {e}"))
}

/// Components `deploy/setup.sh` accepts (the labels of its case arms).
fn setup_components() -> BTreeSet<String> {
    let text = read(&deploy().join("setup.sh"));
    let re = Regex::new(r"(?m)^\s*([a-z0-9|_-]+)\)").expect("regex");
    re.captures_iter(&text).flat_map(|c| c[1].split('|').map(String::from).collect::<Vec<_>>()).collect()
}

fn docker(errors: &mut Vec<String>) -> Vec<Invocation> {
    const KEYWORDS: &[&str] = &[
        "FROM",
        "ARG",
        "ENV",
        "RUN",
        "COPY",
        "ADD",
        "EXPOSE",
        "USER",
        "WORKDIR",
        "CMD",
        "ENTRYPOINT",
        "LABEL",
        "VOLUME",
        "HEALTHCHECK",
        "SHELL",
        "STOPSIGNAL",
        "ONBUILD",
    ];
    let (ins, stages) = dockerfile();
    let name = "deploy/Dockerfile";
    let mut all = Vec::new();
    let global_args: Vec<String> = ins.iter().filter(|i| i.keyword == "GLOBAL-ARG").map(|i| i.rest.clone()).collect();
    let md_features: BTreeSet<String> = cargo_toml("md-worker/Cargo.toml")
        .get("features")
        .and_then(|f| f.as_table())
        .map(|t| t.keys().cloned().collect())
        .unwrap_or_default();
    let packages: BTreeMap<String, Vec<String>> = ["orchestrator", "md-worker"]
        .iter()
        .map(|d| {
            let t = cargo_toml(&format!("{d}/Cargo.toml"));
            let pkg = t.get("package").and_then(|p| p.get("name")).and_then(|n| n.as_str()).unwrap_or("").to_string();
            let bins = t
                .get("bin")
                .and_then(|b| b.as_array())
                .map(|a| a.iter().filter_map(|b| b.get("name")?.as_str().map(String::from)).collect())
                .unwrap_or_default();
            (pkg, bins)
        })
        .collect();
    let ignore: Vec<String> = std::fs::read_to_string(repo().join(".dockerignore"))
        .unwrap_or_default()
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(String::from)
        .collect();
    let args_use = Regex::new(r"\$\{?([A-Z_][A-Z0-9_]*)").expect("regex");
    let features_case = Regex::new(r"\*,([a-z0-9_-]+),\*\)").expect("regex");
    let setup_call = Regex::new(r"setup\.sh\s+([a-z0-9_-]+)").expect("regex");
    let mount = Regex::new(r"--mount=\S+").expect("regex");
    if stages.len() < 2 {
        errors.push(format!("{name}: not multi-stage ({} stage)", stages.len()));
    }
    for i in ins.iter().filter(|i| i.keyword != "GLOBAL-ARG") {
        let at = format!("{name}:{}", i.line);
        if !KEYWORDS.contains(&i.keyword.as_str()) {
            errors.push(format!("{at}: unknown instruction {}", i.keyword));
            continue;
        }
        // Build arguments: declared in scope (global for FROM, the stage's own otherwise).
        let scope: Vec<String> = if i.keyword == "FROM" {
            global_args.clone()
        } else {
            stages.get(i.stage.wrapping_sub(1)).map(|s| s.1.clone()).unwrap_or_default()
        };
        let env_names: Vec<String> = ins
            .iter()
            .filter(|e| e.keyword == "ENV" && e.stage == i.stage)
            .flat_map(|e| e.rest.split_whitespace().filter_map(|kv| kv.split('=').next().map(String::from)).collect::<Vec<_>>())
            .collect();
        for c in args_use.captures_iter(&i.rest) {
            let v = &c[1];
            // Shell variables in RUN (lower-case) are not matched; upper-case ones must be
            // build arguments or ENV of the stage.
            if !scope.iter().any(|a| a == v) && !env_names.iter().any(|e| e == v) && !["PATH", "HOME", "LD_LIBRARY_PATH"].contains(&v) {
                errors
                    .push(format!("{at}: {} uses ${v}, which is not an ARG in scope (a stage sees only the ARGs it declares)", i.keyword));
            }
        }
        match i.keyword.as_str() {
            "COPY" | "ADD" => {
                let w: Vec<&str> = i.rest.split_whitespace().collect();
                let from = w.iter().find_map(|x| x.strip_prefix("--from="));
                let paths: Vec<&str> = w.iter().filter(|x| !x.starts_with("--")).copied().collect();
                match from {
                    Some(stage) => {
                        if !stages[..i.stage.saturating_sub(1)].iter().any(|s| s.0 == stage) {
                            errors.push(format!("{at}: COPY --from={stage}: no earlier stage of that name"));
                        }
                    }
                    None => {
                        for src in &paths[..paths.len().saturating_sub(1)] {
                            if *src != "." && !repo().join(src).exists() {
                                errors.push(format!("{at}: COPY source {src} does not exist in the repository"));
                            }
                            for pat in &ignore {
                                let pat = pat.trim_start_matches("**/");
                                if *src != "." && (src == &pat || src.starts_with(&format!("{pat}/"))) {
                                    errors.push(format!("{at}: COPY source {src} is excluded by .dockerignore ({pat})"));
                                }
                            }
                        }
                    }
                }
            }
            "RUN" => {
                let body = mount.replace_all(&i.rest, "");
                for c in features_case.captures_iter(&body) {
                    if !md_features.contains(&c[1]) {
                        errors.push(format!(
                            "{at}: FEATURES value {} is not a cargo feature of md-worker (it has: {})",
                            &c[1],
                            md_features.iter().cloned().collect::<Vec<_>>().join(", ")
                        ));
                    }
                }
                for c in setup_call.captures_iter(&body) {
                    if !setup_components().contains(&c[1]) {
                        errors.push(format!(
                            "{at}: deploy/setup.sh has no component {} (it has: {})",
                            &c[1],
                            setup_components().into_iter().collect::<Vec<_>>().join(", ")
                        ));
                    }
                }
                let words = shell_words(&body, &BTreeMap::new());
                // cargo build: packages and binaries that exist.
                let mut in_cargo = false;
                for (k, w) in words.iter().enumerate() {
                    if is_separator(w) {
                        in_cargo = false;
                    } else if basename(w) == "cargo" {
                        in_cargo = true;
                    }
                    if !in_cargo {
                        continue;
                    }
                    if w == "-p" || w == "--package" {
                        let pkg = words.get(k + 1).cloned().unwrap_or_default();
                        if !packages.contains_key(&pkg) {
                            errors.push(format!("{at}: cargo -p {pkg}: no such package here"));
                        }
                    }
                    if w == "--bin" {
                        let bin = words.get(k + 1).cloned().unwrap_or_default();
                        if !packages.values().any(|b| b.contains(&bin)) {
                            errors.push(format!("{at}: cargo --bin {bin}: no such binary"));
                        }
                    }
                }
                all.extend(invocations(&words, &at, errors));
            }
            "CMD" | "ENTRYPOINT" => {
                let words: Vec<String> = match serde_json::from_str::<Vec<String>>(&i.rest) {
                    Ok(v) => v,
                    Err(_) => shell_words(&i.rest, &BTreeMap::new()),
                };
                if !words.first().is_some_and(|w| programs().contains_key(basename(w))) {
                    errors.push(format!("{at}: {} runs {:?}, not mscale or md-worker", i.keyword, words.first()));
                }
                all.extend(invocations(&words, &at, errors));
            }
            _ => {}
        }
    }
    // The runtime image holds both programs on PATH, copied from what the build stage built.
    let last = stages.len();
    for (bin, _) in PROGRAMS {
        let copied = ins.iter().any(|i| {
            i.stage == last
                && i.keyword == "COPY"
                && i.rest.contains("--from=")
                && i.rest.split_whitespace().any(|w| basename(w) == bin)
                && i.rest.trim_end().ends_with("/usr/local/bin/")
        });
        if !copied {
            errors.push(format!("{name}: the runtime stage does not copy {bin} into /usr/local/bin/"));
        }
        let built = ins.iter().any(|i| i.keyword == "RUN" && i.rest.contains("cargo build") && i.rest.contains(&format!("--bin {bin}")));
        if !built {
            errors.push(format!("{name}: no stage builds --bin {bin}"));
        }
    }
    if !ins.iter().any(|i| i.keyword == "RUN" && i.rest.contains("deploy/setup.sh"))
        && !ins.iter().any(|i| i.keyword == "RUN" && i.rest.contains("setup.sh"))
    {
        errors.push(format!("{name}: does not call deploy/setup.sh"));
    }
    all
}

// ---------------------------------------------------------------- the checks

fn every_invocation(errors: &mut Vec<String>) -> Vec<Invocation> {
    let mut all = slurm(errors);
    all.extend(systemd(errors));
    all.extend(k8s(errors));
    all.extend(docker(errors));
    all
}

#[test]
fn every_binary_subcommand_and_flag_exists() {
    let mut errors = Vec::new();
    let all = every_invocation(&mut errors);
    // The deployments run what the issue asks for.
    for (program, command, wanted) in [
        ("mscale", "serve", &["listen", "state-dir", "token-file", "tls-cert", "tls-key"][..]),
        ("md-worker", "serve", &["listen", "device", "orchestrator", "advertise", "token-file", "ca-file"][..]),
        ("mscale", "submit", &["server", "token-file", "ca-file"][..]),
        ("mscale", "health", &["server", "token-file", "ca-file"][..]),
    ] {
        let runs: Vec<&Invocation> = all.iter().filter(|i| i.is(program, command)).collect();
        if runs.is_empty() {
            errors.push(format!("no deployment file runs `{program} {command}`"));
        }
        for flag in wanted {
            if !runs.iter().any(|i| i.flags.iter().any(|(f, _)| f == flag)) {
                errors.push(format!("no deployment file passes `{program} {command} --{flag}`"));
            }
        }
    }
    for inv in all.iter().filter(|i| i.is("md-worker", "serve")) {
        if let Some(d) = inv.flag("device").filter(|d| !["auto", "cpu", "cuda"].contains(d)) {
            errors.push(format!("{}: md-worker serve --device {d}: expected auto, cpu or cuda", inv.origin));
        }
    }
    report("binaries, subcommands and flags in deploy/", errors);
}

/// The port of HOST:PORT or SCHEME://HOST:PORT[/...] when it is a number.
fn port(addr: &str) -> Option<u16> {
    let a = addr.split("://").last()?.split('/').next()?;
    a.rsplit_once(':')?.1.parse().ok()
}

#[test]
fn ports_agree() {
    let mut errors = Vec::new();
    let all = every_invocation(&mut errors);
    errors.clear(); // flags are the other test's business
    let default = Regex::new(r"\[default: [^\]]*:(\d+)\]").expect("regex");
    let serve_help = &programs()["mscale"].subcommands["serve"].help;
    let listen_line = serve_help.lines().find(|l| l.contains("--listen")).unwrap_or("");
    let default_port: Option<u16> = default.captures(listen_line).and_then(|c| c[1].parse().ok());
    let mut orchestrator = BTreeSet::new();
    for inv in all.iter().filter(|i| i.is("mscale", "serve")) {
        match inv.flag("listen").and_then(port) {
            Some(p) => {
                orchestrator.insert(p);
            }
            None => errors.push(format!("{}: mscale serve without a --listen HOST:PORT", inv.origin)),
        }
    }
    if orchestrator.len() != 1 {
        errors.push(format!("the orchestrator listens on different ports across files: {orchestrator:?}"));
    }
    let p = orchestrator.iter().next().copied().unwrap_or(0);
    if default_port.is_some_and(|d| d != p) {
        errors.push(format!("the orchestrator port {p} is not mscale's default {default_port:?}"));
    }
    for inv in &all {
        for flag in ["server", "orchestrator"] {
            if let Some(v) = inv.flag(flag) {
                match port(v) {
                    Some(q) if q != p => {
                        errors.push(format!("{}: --{flag} {v}: port {q}, but the orchestrator listens on {p}", inv.origin))
                    }
                    None if !v.contains('$') => errors.push(format!("{}: --{flag} {v}: no port", inv.origin)),
                    _ => {}
                }
            }
        }
    }
    let mut worker_ports = BTreeSet::new();
    for inv in all.iter().filter(|i| i.is("md-worker", "serve")) {
        let listen = inv.flag("listen").unwrap_or("").rsplit(':').next().unwrap_or("").to_string();
        let advertise = inv.flag("advertise").unwrap_or("").rsplit(':').next().unwrap_or("").to_string();
        if listen.is_empty() || listen != advertise {
            errors.push(format!("{}: md-worker serve listens on port {listen:?} but advertises {advertise:?}", inv.origin));
        }
        if let Ok(p) = listen.parse::<u16>() {
            worker_ports.insert(p);
        }
    }
    // Kubernetes: Services, container ports and probes.
    let docs = k8s_docs();
    let cs = containers(&docs);
    for c in &cs {
        let ports: Vec<(String, u16)> =
            seq(c.container.get("ports")).iter().map(|p| (st(p, &["name"]), st(p, &["containerPort"]).parse().unwrap_or(0))).collect();
        let mut words = words_of(c.container.get("command"));
        words.extend(words_of(c.container.get("args")));
        let listen = invocations(&words, &c.origin, &mut Vec::new()).iter().find_map(|i| i.flag("listen").and_then(port));
        if let Some(l) = listen.filter(|l| !ports.iter().any(|(_, p)| p == l)) {
            errors.push(format!("{}: listens on {l} but declares containerPorts {ports:?}", c.origin));
        }
        for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
            for kind in ["grpc", "tcpSocket", "httpGet"] {
                if let Some(v) = s(&c.container, &[probe, kind, "port"]) {
                    let ok = match v {
                        Value::Number(n) => ports.iter().any(|(_, p)| Some(*p as u64) == n.as_u64()),
                        Value::String(name) => ports.iter().any(|(n, _)| n == name),
                        _ => false,
                    };
                    if !ok {
                        errors.push(format!("{}: {probe} probes port {v:?}, which the container does not declare", c.origin));
                    }
                }
            }
        }
        for (_, cp) in &ports {
            if !exposed().contains(cp) {
                errors.push(format!("{}: containerPort {cp} is not EXPOSEd by deploy/Dockerfile ({:?})", c.origin, exposed()));
            }
        }
    }
    for (file, svc) in docs.iter().filter(|(_, d)| st(d, &["kind"]) == "Service") {
        let name = st(svc, &["metadata", "name"]);
        let selector = s(svc, &["spec", "selector"]).cloned().unwrap_or(Value::Null);
        let chosen: Vec<&Container> =
            cs.iter().filter(|c| labels_match(&selector, s(&c.workload, &["spec", "template", "metadata", "labels"]))).collect();
        if chosen.is_empty() {
            errors.push(format!("{file}: Service {name} selects no pod template"));
        }
        for sp in seq(s(svc, &["spec", "ports"])) {
            let port_n: u16 = st(&sp, &["port"]).parse().unwrap_or(0);
            let target = s(&sp, &["targetPort"]).cloned().unwrap_or(Value::Number(port_n.into()));
            for c in &chosen {
                let resolved = seq(c.container.get("ports"))
                    .iter()
                    .find(|p| match &target {
                        Value::String(t) => st(p, &["name"]) == *t,
                        Value::Number(n) => st(p, &["containerPort"]) == n.to_string(),
                        _ => false,
                    })
                    .map(|p| st(p, &["containerPort"]));
                match resolved {
                    None => errors.push(format!("{file}: Service {name} targets port {target:?}, which {} does not declare", c.origin)),
                    Some(cp) if cp != port_n.to_string() => errors
                        .push(format!("{file}: Service {name} port {port_n} maps to containerPort {cp}: clients and the server disagree")),
                    _ => {}
                }
            }
        }
    }
    for p in worker_ports.iter().chain(orchestrator.iter()) {
        if !exposed().contains(p) {
            errors.push(format!("deploy/Dockerfile does not EXPOSE port {p}"));
        }
    }
    report("ports in deploy/", errors);
}

fn labels_match(selector: &Value, labels: Option<&Value>) -> bool {
    let (Some(sel), Some(labels)) = (selector.as_mapping(), labels.and_then(|l| l.as_mapping())) else { return false };
    !sel.is_empty() && sel.iter().all(|(k, v)| labels.get(k) == Some(v))
}

#[test]
fn kubernetes_manifests_hang_together() {
    let mut errors = Vec::new();
    let docs = k8s_docs();
    let defined = |kind: &str| -> BTreeMap<String, Value> {
        docs.iter().filter(|(_, d)| st(d, &["kind"]) == kind).map(|(_, d)| (st(d, &["metadata", "name"]), d.clone())).collect()
    };
    let secrets = defined("Secret");
    let claims = defined("PersistentVolumeClaim");
    let services = defined("Service");
    for (file, d) in &docs {
        let kind = st(d, &["kind"]);
        if kind.is_empty() || (st(d, &["apiVersion"]).is_empty() && kind != "Kustomization") {
            errors.push(format!("{file}: a document without kind/apiVersion"));
        }
        if kind == "Kustomization" {
            for r in words_of(d.get("resources")) {
                if !deploy().join("k8s").join(&r).exists() {
                    errors.push(format!("{file}: resource {r} does not exist"));
                }
            }
        }
        if ["Deployment", "StatefulSet"].contains(&kind.as_str())
            && !labels_match(
                s(d, &["spec", "selector", "matchLabels"]).unwrap_or(&Value::Null),
                s(d, &["spec", "template", "metadata", "labels"]),
            )
        {
            errors.push(format!("{file}: {kind} selector does not match its pod template's labels"));
        }
        if kind == "StatefulSet" {
            let svc = st(d, &["spec", "serviceName"]);
            match services.get(&svc) {
                Some(s_) if st(s_, &["spec", "clusterIP"]) == "None" => {}
                _ => errors.push(format!("{file}: StatefulSet serviceName {svc:?} is not a headless Service here")),
            }
        }
    }
    let image_dirs = image_copies();
    let k8s_var = Regex::new(r"\$\(([A-Za-z_0-9]+)\)").expect("regex");
    for c in containers(&docs) {
        let kind = st(&c.workload, &["kind"]);
        let mounts: Vec<(String, String)> =
            seq(c.container.get("volumeMounts")).iter().map(|m| (st(m, &["mountPath"]), st(m, &["name"]))).collect();
        let volumes: BTreeMap<String, Value> =
            seq(s(&c.workload, &["spec", "template", "spec", "volumes"])).iter().map(|v| (st(v, &["name"]), v.clone())).collect();
        let env: BTreeSet<String> = seq(c.container.get("env")).iter().map(|e| st(e, &["name"])).collect();
        for (_, vol) in &mounts {
            if !volumes.contains_key(vol) {
                errors.push(format!("{}: mounts volume {vol}, which the pod does not define", c.origin));
            }
        }
        for v in volumes.values() {
            if let Some(name) = s(v, &["secret", "secretName"]).and_then(|n| n.as_str()) {
                match secrets.get(name) {
                    None => errors.push(format!("{}: secret {name} is not defined in deploy/k8s (secrets.example.yaml)", c.origin)),
                    Some(sec) => {
                        for item in seq(s(v, &["secret", "items"])) {
                            let key = st(&item, &["key"]);
                            if s(sec, &["stringData", &key]).is_none() && s(sec, &["data", &key]).is_none() {
                                errors.push(format!("{}: secret {name} has no key {key}", c.origin));
                            }
                        }
                    }
                }
            }
            if let Some(claim) = s(v, &["persistentVolumeClaim", "claimName"]).and_then(|n| n.as_str()).filter(|c| !claims.contains_key(*c))
            {
                errors.push(format!("{}: PersistentVolumeClaim {claim} is not defined", c.origin));
            }
        }
        // Every absolute path a command names is in a mount (a secret's key) or in the image.
        let mut words = words_of(c.container.get("command"));
        words.extend(words_of(c.container.get("args")));
        let mut runs = invocations(&words, &c.origin, &mut Vec::new());
        for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
            runs.extend(invocations(&words_of(s(&c.container, &[probe, "exec", "command"])), &c.origin, &mut Vec::new()));
        }
        for inv in &runs {
            let values = inv.flags.iter().filter_map(|(_, v)| v.clone()).chain(inv.positionals.iter().cloned());
            for path in values.filter(|v| v.starts_with('/')) {
                if let Some((mount, vol)) = mounts.iter().find(|(m, _)| path == *m || path.starts_with(&format!("{m}/"))) {
                    let file = path[mount.len()..].trim_start_matches('/');
                    let secret = volumes.get(vol).and_then(|v| Some((v, s(v, &["secret", "secretName"])?.as_str()?)));
                    if let Some((v, name)) = secret {
                        let items = seq(s(v, &["secret", "items"]));
                        let has = if items.is_empty() {
                            secrets
                                .get(name)
                                .is_some_and(|sec| s(sec, &["stringData", file]).is_some() || s(sec, &["data", file]).is_some())
                        } else {
                            items.iter().any(|i| st(i, &["path"]) == file)
                        };
                        if !has {
                            errors.push(format!("{}: {path}: secret {name} mounted at {mount} has no file {file}", c.origin));
                        }
                    }
                } else if let Some((src, dest)) = image_dirs.iter().find(|(_, d)| path.starts_with(&format!("{d}/"))) {
                    let in_repo = repo().join(src).join(&path[dest.len() + 1..]);
                    if !in_repo.exists() {
                        errors.push(format!("{}: {path} is not in the image ({} does not exist)", c.origin, rel(&in_repo)));
                    }
                } else {
                    errors.push(format!("{}: {path} is neither mounted nor copied into the image", c.origin));
                }
            }
            for v in inv.flags.iter().filter_map(|(_, v)| v.as_deref()) {
                for var in k8s_var.captures_iter(v) {
                    if !env.contains(&var[1]) {
                        errors.push(format!("{}: $({}) is not in the container's env", c.origin, &var[1]));
                    }
                }
            }
            if inv.is("md-worker", "serve") {
                let host = inv.flag("orchestrator").and_then(|u| u.split("://").last()).and_then(|h| h.split(':').next()).unwrap_or("");
                if !services.contains_key(host) {
                    errors.push(format!("{}: --orchestrator host {host:?} is not a Service here", c.origin));
                }
                let advertised = inv.flag("advertise").unwrap_or("");
                let sts_service = st(&c.workload, &["spec", "serviceName"]);
                if kind == "StatefulSet" && !advertised.contains(&format!(".{sts_service}:")) {
                    errors.push(format!("{}: --advertise {advertised} is not a name under the headless Service {sts_service}", c.origin));
                }
                if inv.flag("device") == Some("cuda") && s(&c.container, &["resources", "limits", "nvidia.com/gpu"]).is_none() {
                    errors.push(format!("{}: md-worker --device cuda without a nvidia.com/gpu limit", c.origin));
                }
            }
        }
        if kind == "Deployment" && runs.iter().any(|i| i.is("mscale", "serve")) {
            for probe in ["readinessProbe", "livenessProbe"] {
                let w = words_of(s(&c.container, &[probe, "exec", "command"]));
                let inv = invocations(&w, &c.origin, &mut Vec::new());
                if !inv.iter().any(|i| i.is("mscale", "health")) {
                    errors.push(format!("{}: {probe} is not an exec probe running `mscale health`", c.origin));
                }
            }
        }
        if kind == "StatefulSet" && s(&c.container, &["resources", "limits", "nvidia.com/gpu"]).is_none() {
            errors.push(format!("{}: a worker StatefulSet without a nvidia.com/gpu request", c.origin));
        }
    }
    for kind in ["Deployment", "Service", "PersistentVolumeClaim", "StatefulSet", "Secret"] {
        if defined(kind).is_empty() {
            errors.push(format!("deploy/k8s defines no {kind}"));
        }
    }
    // kubectl (where installed) builds the kustomization.
    match Command::new("kubectl").args(["kustomize"]).arg(deploy().join("k8s")).output() {
        Ok(o) if !o.status.success() => errors.push(format!("kubectl kustomize deploy/k8s: {}", String::from_utf8_lossy(&o.stderr))),
        Ok(_) => {}
        Err(_) => eprintln!("deploy: kubectl is not installed; the kustomization gets the parser's checks only"),
    }
    report("Kubernetes manifests", errors);
}

#[test]
fn slurm_scripts_parse() {
    let mut errors = Vec::new();
    let runs = slurm(&mut errors);
    for s_ in ["mscale serve", "mscale submit", "mscale watch"] {
        if !runs.iter().any(|i| format!("{} {}", i.program, i.command.join(" ")) == s_) {
            errors.push(format!("no Slurm script runs `{s_}`"));
        }
    }
    // Worker pools are MPI jobs started with srun.
    for inv in runs.iter().filter(|i| i.is("md-worker", "serve")) {
        match &inv.wrapper {
            Some((w, opts)) if w == "srun" && opts.iter().any(|o| o.starts_with("--mpi")) => {}
            _ => errors.push(format!("{}: md-worker serve is not started as an MPI job by srun --mpi=...", inv.origin)),
        }
    }
    for p in files("", &[".sh"]) {
        bash_n(&p, &mut errors);
    }
    report("Slurm scripts", errors);
}

#[test]
fn systemd_units_are_well_formed() {
    let mut errors = Vec::new();
    let runs = systemd(&mut errors);
    for s_ in ["mscale serve", "md-worker serve"] {
        if !runs.iter().any(|i| format!("{} {}", i.program, i.command.join(" ")) == s_) {
            errors.push(format!("no systemd unit runs `{s_}`"));
        }
    }
    if !deploy().join("systemd/md-worker@.service").exists() {
        errors.push("deploy/systemd/md-worker@.service (the worker template unit) is missing".into());
    }
    report("systemd units", errors);
}

#[test]
fn dockerfile_names_real_things() {
    let mut errors = Vec::new();
    docker(&mut errors);
    report("deploy/Dockerfile", errors);
}

#[test]
fn repository_paths_exist() {
    let mut errors = Vec::new();
    let re =
        Regex::new(r#"(?:^|[\s"'=/}:(])((?:scenes|deploy|md-worker/potentials|tests/data|scripts)(?:/[A-Za-z0-9_.@-]+)*)"#).expect("regex");
    let mut all: Vec<PathBuf> = Vec::new();
    for dir in ["slurm", "k8s", "systemd"] {
        all.extend(files(dir, &[""]));
    }
    all.push(deploy().join("Dockerfile"));
    all.push(deploy().join("make-certs.sh"));
    let mut scenes = BTreeSet::new();
    for p in &all {
        let text = read(p);
        for c in re.captures_iter(&text) {
            let path = c[1].trim_end_matches('.').to_string();
            if !repo().join(&path).exists() {
                errors.push(format!("{}: names {path}, which does not exist in the repository", rel(p)));
            } else if path.starts_with("scenes/") && path.ends_with(".toml") {
                scenes.insert(path);
            }
        }
    }
    if scenes.is_empty() {
        errors.push("no deployment file names a scene to submit".into());
    }
    // A named scene loads, with every file it names (potentials): `mscale check`.
    for scene in scenes {
        let o = Command::new(binary("mscale", "orchestrator")).args(["check", &scene]).current_dir(repo()).output().expect("mscale check");
        if !o.status.success() {
            errors.push(format!("mscale check {scene}: {}", String::from_utf8_lossy(&o.stderr)));
        }
    }
    report("repository paths in deploy/", errors);
}

#[test]
fn readme_says_these_files_are_statically_checked() {
    let readme = read(&repo().join("README.md"));
    let section = readme.split("\n## Deployment").nth(1).expect("README.md has a `## Deployment` section");
    let section = section.split("\n## ").next().unwrap_or("");
    assert!(
        section.contains("statically") && section.contains("tests/deploy.rs"),
        "README's Deployment section must say the files are only statically checked (tests/deploy.rs)"
    );
}

/// The orchestrator command and the health probe of the Kubernetes Deployment, run here with
/// certificates from deploy/make-certs.sh: TLS on a non-loopback address, probe over
/// https://localhost. Paths under /etc/mscale and /var/lib/mscale move into a temporary
/// directory; the port becomes 0 (a free one) and the probe follows it.
#[test]
fn kubernetes_orchestrator_and_probe_commands_run() {
    use std::io::BufRead;
    let docs = k8s_docs();
    let c = containers(&docs).into_iter().find(|c| st(&c.workload, &["kind"]) == "Deployment").expect("an orchestrator Deployment");
    let tmp = tempfile::tempdir().expect("tempdir");
    let root = tmp.path();
    let certs = root.join("etc/mscale/tls");
    let o = Command::new("bash")
        .arg(deploy().join("make-certs.sh"))
        .arg(&certs)
        .arg("mscale-orchestrator")
        .output()
        .expect("bash make-certs.sh");
    assert!(o.status.success(), "make-certs.sh: {}", String::from_utf8_lossy(&o.stderr));
    std::fs::create_dir_all(root.join("etc/mscale/token")).expect("mkdir");
    std::fs::write(root.join("etc/mscale/token/token"), "deploy-test-token-0123456789\n").expect("token");
    let map = |w: &String| -> String {
        let w = w
            .replace("/etc/mscale", &root.join("etc/mscale").to_string_lossy())
            .replace("/var/lib/mscale", &root.join("state").to_string_lossy());
        if w.starts_with("0.0.0.0:") { "0.0.0.0:0".to_string() } else { w }
    };
    let mut words: Vec<String> =
        words_of(c.container.get("command")).iter().chain(words_of(c.container.get("args")).iter()).map(map).collect();
    assert_eq!(basename(&words[0]), "mscale");
    words[0] = binary("mscale", "orchestrator").to_string_lossy().into_owned();
    let log = root.join("serve.log");
    let mut child = Command::new(&words[0])
        .args(&words[1..])
        .stdout(std::process::Stdio::piped())
        .stderr(std::fs::File::create(&log).expect("log"))
        .spawn()
        .expect("start mscale serve");
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("stdout")).read_line(&mut line).expect("read");
    let addr = line.trim().rsplit(' ').next().unwrap_or("").to_string();
    let served_port = port(&addr);
    let result = (|| {
        let port_n = served_port.ok_or_else(|| {
            format!("mscale serve did not say where it listens: {line:?}; {}", std::fs::read_to_string(&log).unwrap_or_default())
        })?;
        for probe in ["startupProbe", "readinessProbe", "livenessProbe"] {
            let mut w: Vec<String> = words_of(s(&c.container, &[probe, "exec", "command"])).iter().map(map).collect();
            if w.is_empty() {
                continue;
            }
            w = w
                .into_iter()
                .map(|x| if x.starts_with("https://localhost:") { format!("https://localhost:{port_n}") } else { x })
                .collect();
            let o = Command::new(binary("mscale", "orchestrator"))
                .args(&w[1..])
                .env_remove("MSCALE_CA_FILE")
                .output()
                .map_err(|e| e.to_string())?;
            if !o.status.success() || !String::from_utf8_lossy(&o.stdout).contains("SERVING") {
                return Err(format!(
                    "{probe} {w:?}: exit {:?}, {}{}",
                    o.status.code(),
                    String::from_utf8_lossy(&o.stdout),
                    String::from_utf8_lossy(&o.stderr)
                ));
            }
        }
        Ok(())
    })();
    let _ = child.kill();
    let _ = child.wait();
    if let Err(e) = result {
        panic!("{e}\nserve log: {}", std::fs::read_to_string(&log).unwrap_or_default());
    }
}
