//! A resume never drops what the command line asked: every setting a `--config` file (or an
//! option) gives is compared with the run's own, and a resume that would silently keep another
//! value is refused, naming each setting. The total iterations may change mid-run (a resume
//! trains on to the new total); `--no-compact` applies after training.

use serde::Serialize;
use serde_json::Value;
use std::path::Path;

/// Settings a resume may change: the run's total iterations.
pub const LEGAL: [&str; 1] = ["iters"];

/// One setting the command line asks for and the run's own value.
#[derive(Debug, PartialEq)]
pub struct Changed {
    /// Dotted path, e.g. `field.view_channels`.
    pub key: String,
    pub asked: Value,
    pub run: Value,
}

/// The settings of `asked` (a user's config as written: only the keys it names) whose value is
/// not the run's (`stored`), legal ones (`LEGAL`) left out. Nested objects are compared key by
/// key; a key the run does not have counts as changed.
pub fn changed(asked: &Value, stored: &Value) -> Vec<Changed> {
    let mut out = Vec::new();
    walk("", asked, stored, &mut out);
    out.retain(|c| !LEGAL.contains(&c.key.as_str()));
    out
}

fn walk(prefix: &str, asked: &Value, stored: &Value, out: &mut Vec<Changed>) {
    match (asked, stored) {
        (Value::Object(a), Value::Object(s)) => {
            for (k, v) in a {
                let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                walk(&key, v, s.get(k).unwrap_or(&Value::Null), out);
            }
        }
        (a, s) if same(a, s) => {}
        (a, s) => out.push(Changed { key: prefix.to_string(), asked: a.clone(), run: s.clone() }),
    }
}

/// Equal values, numbers by value (1 and 1.0 are the same setting).
fn same(a: &Value, s: &Value) -> bool {
    match (a, s) {
        (Value::Number(a), Value::Number(s)) => a.as_f64() == s.as_f64(),
        (Value::Array(a), Value::Array(s)) => a.len() == s.len() && a.iter().zip(s).all(|(a, s)| same(a, s)),
        (Value::Object(a), Value::Object(s)) => {
            a.len() == s.len() && a.iter().all(|(k, v)| s.get(k).is_some_and(|w| same(v, w)))
        }
        (a, s) => a == s,
    }
}

/// Refuses a resume of the run whose settings are `stored` (in `stored_path`) when the command
/// line asks for others: the `--config` file's keys (`config`) and the options in `options` (a
/// setting's dotted key, the option as typed, its value). Each differing setting is named, except
/// those the stage sets itself whatever was asked (`resolved(key, asked)`: e.g. taken from the
/// teacher, or "auto").
pub fn refuse_changes(
    stored_path: &Path,
    stored: &impl Serialize,
    config: Option<&Path>,
    options: &[(&str, String, Value)],
    resolved: impl Fn(&str, &Value) -> bool,
) -> anyhow::Result<()> {
    let stored = serde_json::to_value(stored)?;
    let mut problems = Vec::new();
    if let Some(p) = config {
        let asked: Value = model::io::read_json(p)?;
        for c in changed(&asked, &stored).into_iter().filter(|c| !resolved(&c.key, &c.asked)) {
            problems.push(format!("{} sets {} to {}, the run has {}", p.display(), c.key, c.asked, c.run));
        }
    }
    for (key, option, value) in options {
        let mut asked = value.clone();
        for part in key.rsplit('.') {
            asked = serde_json::json!({ part: asked });
        }
        for c in changed(&asked, &stored).into_iter().filter(|c| !resolved(&c.key, &c.asked)) {
            problems.push(format!("{option} asks {} = {}, the run has {}", c.key, c.asked, c.run));
        }
    }
    if problems.is_empty() {
        return Ok(());
    }
    anyhow::bail!(
        "--resume keeps the run's settings ({}), but the command line asks for others: {}. Resume without them, \
         or train a new run into another --out",
        stored_path.display(),
        problems.join("; ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn only_the_keys_asked_and_not_the_legal_ones() {
        let stored = json!({"iters": 100, "lr": 0.01, "field": {"view_channels": 32, "grid": 27}, "bg": [1.0, 1.0]});
        // the same values (1 written as 1.0 too), the legal total: nothing changed
        let same = json!({"iters": 5000, "lr": 0.01, "field": {"view_channels": 32.0}, "bg": [1, 1]});
        assert_eq!(changed(&same, &stored), vec![]);
        let asked = json!({"lr": 0.02, "field": {"view_channels": 16}, "bg": [0, 0], "typo": 1});
        let mut keys: Vec<String> = changed(&asked, &stored).into_iter().map(|c| c.key).collect();
        keys.sort();
        assert_eq!(keys, ["bg", "field.view_channels", "lr", "typo"]);
    }
}
