//! The parse layer: `--set` overrides applied to the TOML text, and the locator that finds the
//! line (or the `--set`) of a dotted key for the messages.

use super::names::Unknown;
use super::{LoadedScene, Scene, SceneError};
use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

pub(super) struct Locator<'a> {
    pub(super) file: String,
    pub(super) text: &'a str,
    pub(super) overrides: &'a BTreeMap<String, String>,
}

impl Locator<'_> {
    fn location(&self, key: &str) -> String {
        if let Some(v) = self.overrides.get(key) {
            return format!("--set {key}={v}");
        }
        // An element of an overridden array (`output.dump_points[1]`): the --set of the array.
        if let Some((array, _)) = key.split_once('[')
            && let Some(v) = self.overrides.get(array)
        {
            return format!("--set {array}={v}");
        }
        line_of(self.text, key).map(|l| format!("line {l}")).unwrap_or_default()
    }

    pub(super) fn err(&self, key: &str, value: impl fmt::Display, problem: impl Into<String>) -> SceneError {
        SceneError {
            file: self.file.clone(),
            location: self.location(key),
            key: key.into(),
            value: value.to_string(),
            problem: problem.into(),
        }
    }
}

/// Line (1-based) of a dotted key in TOML text, if it is written there.
fn line_of(text: &str, key: &str) -> Option<usize> {
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    let mut item = doc.as_item();
    let mut span = None;
    for part in key.split('.') {
        let (name, index) = match part.split_once('[') {
            Some((n, rest)) => (n, rest.trim_end_matches(']').parse::<usize>().ok()),
            None => (part, None),
        };
        let table = item.as_table_like()?;
        let (k, next) = table.get_key_value(name)?;
        span = k.span().or(span);
        item = next;
        if let Some(i) = index
            && let Some(v) = item.as_array().and_then(|a| a.get(i))
        {
            span = v.span().or(span);
        }
        if let Some(s) = item.span() {
            span = Some(span.map_or(s.clone(), |old: std::ops::Range<usize>| old.start.min(s.start)..s.end));
        }
    }
    let start = span?.start;
    Some(text[..start.min(text.len())].matches('\n').count() + 1)
}

/// Applies `key=value` overrides to TOML text. Values are read as TOML (`300`, `"fcc"`,
/// `[1.0, 2.0]`, `true`), and as a plain string when they are not valid TOML.
pub fn apply_overrides(file: &str, text: &str, sets: &[String]) -> Result<(String, BTreeMap<String, String>), SceneError> {
    let mut doc: toml_edit::DocumentMut = text.parse().map_err(|e: toml_edit::TomlError| SceneError {
        file: file.into(),
        location: String::new(),
        key: String::new(),
        value: String::new(),
        problem: format!("not valid TOML: {e}"),
    })?;
    let mut applied = BTreeMap::new();
    for set in sets {
        let bad = |problem: &str| SceneError {
            file: file.into(),
            location: format!("--set {set}"),
            key: String::new(),
            value: String::new(),
            problem: problem.into(),
        };
        let (key, raw) = set.split_once('=').ok_or_else(|| bad("expected --set dotted.key=value"))?;
        let key = key.trim();
        if key.is_empty() || key.split('.').any(str::is_empty) {
            return Err(bad("the key is empty or has an empty part; expected for example bodies.left.temperature_k=300"));
        }
        let value: toml_edit::Value = raw.trim().parse().unwrap_or_else(|_| toml_edit::Value::from(raw.trim()));
        let parts: Vec<&str> = key.split('.').collect();
        let mut table = doc.as_table_mut() as &mut dyn toml_edit::TableLike;
        for part in &parts[..parts.len() - 1] {
            if table.get(part).is_none() {
                table.insert(part, toml_edit::Item::Table(toml_edit::Table::new()));
            }
            table = table
                .get_mut(part)
                .and_then(|i| i.as_table_like_mut())
                .ok_or_else(|| bad(&format!("`{part}` is a value, not a table, so `{key}` cannot be set")))?;
        }
        table.insert(parts[parts.len() - 1], toml_edit::Item::Value(value));
        applied.insert(key.to_string(), raw.trim().to_string());
    }
    Ok((doc.to_string(), applied))
}

/// Reads, overrides, parses and validates a scene file.
pub fn load(path: &Path, sets: &[String]) -> Result<LoadedScene, SceneError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| SceneError {
        file: file.clone(),
        location: String::new(),
        key: String::new(),
        value: String::new(),
        problem: format!("cannot read the scene file: {e}"),
    })?;
    let default_name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "scene".into());
    parse(&file, &text, sets, path.parent().unwrap_or(Path::new(".")), &default_name)
}

/// Parses and validates scene text; `base` resolves the files it names.
pub fn parse(file: &str, text: &str, sets: &[String], base: &Path, default_name: &str) -> Result<LoadedScene, SceneError> {
    let (text, overrides) = apply_overrides(file, text, sets)?;
    let loc = Locator { file: file.into(), text: &text, overrides: &overrides };
    let mut scene: Scene = toml::from_str(&text).map_err(|e| {
        // A name outside its set: the message validation gives, at the key it was given for.
        if let Some(u) = Unknown::decode(e.message())
            && let Some(key) = e.span().and_then(|s| key_at(&text, s.start, &u.field))
        {
            return loc.err(&key, &u.value, u.allowed);
        }
        let location = e.span().map(|s| format!("line {}", text[..s.start.min(text.len())].matches('\n').count() + 1)).unwrap_or_default();
        let key = e.span().map(|s| text[s.clone()].trim().to_string()).unwrap_or_default();
        let key = if key.len() > 60 || key.contains('\n') { String::new() } else { key };
        SceneError { file: file.into(), location, key, value: String::new(), problem: e.message().to_string() }
    })?;
    if scene.name.is_empty() {
        scene.name = default_name.to_string();
    }
    let (resolved, files) = scene.resolve(&loc, base)?;
    let (dt, steps) = (resolved.dt, resolved.steps);
    Ok(LoadedScene { scene, path: PathBuf::from(file), text, files, dt, steps, resolved })
}

/// The dotted key (`scheme.method`, `bodies.left.material.lattice`) whose value lies at byte
/// `at` of TOML text: the innermost written value there. Where that is a table (the place serde
/// gives for a value of an internally tagged table such as `material`), its entry `field`.
fn key_at(text: &str, at: usize, field: &str) -> Option<String> {
    fn walk(table: &dyn toml_edit::TableLike, at: usize, path: &mut Vec<String>) -> bool {
        for (k, item) in table.iter() {
            path.push(k.to_string());
            let here = item.span().is_some_and(|s| s.contains(&at));
            if let Some(t) = item.as_table_like()
                && walk(t, at, path)
            {
                return true;
            }
            if here {
                return true;
            }
            path.pop();
        }
        false
    }
    let doc = toml_edit::ImDocument::parse(text).ok()?;
    let mut path = Vec::new();
    if !walk(doc.as_item().as_table_like()?, at, &mut path) {
        return None;
    }
    let table = path.iter().try_fold(doc.as_item(), |item, k| item.get(k.as_str()))?;
    if !field.is_empty() && table.is_table_like() && path.last().is_none_or(|last| last != field) {
        path.push(field.to_string());
    }
    Some(path.join("."))
}
