//! ARCHITECTURE.md's module order: inside every crate of the workspace, no module reaches a
//! sibling that reaches it back, directly or round a longer circle. The graph is read from the
//! sources: every `crate::` and `super::` path in code (use statements, their brace groups
//! expanded, and paths written inline), test modules and doc-only imports left out; a path to a
//! parent's re-export (`pub use child::Item`) counts as a path to that child.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The source folders of the workspace's crates, from the repository root; each folder under a
/// crate's `bin/` is a binary crate of its own ([`crates`]).
const CRATES: &[&str] = &[
    "splat_kernels/src",
    "model/base/src",
    "model/data/src",
    "model/llava-onevision/src",
    "model/sam/src",
    "model/core/src",
    "model/viewer/src",
    "train/src",
    "eval/scoring/src",
    "eval/src",
    "src",
    "tests/suite/support",
];

/// [`CRATES`] and the binaries of several files among them (`eval/src/bin/vqa_bench`).
fn crates() -> Vec<String> {
    let mut out = Vec::new();
    for krate in CRATES {
        out.push(krate.to_string());
        let Ok(bins) = std::fs::read_dir(repo().join(krate).join("bin")) else { continue };
        let mut dirs: Vec<String> = bins
            .flatten()
            .filter(|e| e.path().is_dir())
            .map(|e| format!("{krate}/bin/{}", e.file_name().to_string_lossy()))
            .collect();
        dirs.sort();
        out.extend(dirs);
    }
    out
}

type Module = Vec<String>;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let p = e.expect("a directory entry").path();
        if p.is_dir() {
            // binaries are crates of their own
            if p.file_name().is_none_or(|n| n != "bin") {
                rust_files(&p, out);
            }
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// `language/field.rs` -> [language, field]; `language/mod.rs` -> [language]; `lib.rs` -> [].
fn module_of(src: &Path, file: &Path) -> Module {
    let rel = file.strip_prefix(src).expect("a file under its crate");
    let mut m: Module = rel.iter().map(|s| s.to_string_lossy().trim_end_matches(".rs").to_string()).collect();
    if matches!(m.last().map(String::as_str), Some("mod" | "lib" | "main")) {
        m.pop();
    }
    m
}

/// The code of a file without comments, doc-only imports and test modules.
fn code(text: &str) -> String {
    let mut out = String::new();
    let mut skip_next = false;
    for line in text.lines() {
        let t = line.trim_start();
        if t.starts_with("#[cfg(test)]") {
            break; // test modules come last
        }
        if t.starts_with("#[cfg(doc)]") {
            skip_next = true;
            continue;
        }
        if t.starts_with("//") {
            continue;
        }
        if std::mem::take(&mut skip_next) {
            continue;
        }
        let line = line.find("//").map_or(line, |i| &line[..i]);
        out.push_str(line);
        out.push('\n');
    }
    out
}

/// `a::{b, c::{d, e}}` -> `a::b`, `a::c::d`, `a::c::e`.
fn expand(tree: &str) -> Vec<String> {
    let tree: String = tree.chars().filter(|c| !c.is_whitespace()).collect();
    let Some(open) = tree.find('{') else { return vec![tree] };
    let (prefix, rest) = (&tree[..open], &tree[open + 1..tree.len() - 1]);
    let mut parts = Vec::new();
    let (mut depth, mut start) = (0, 0);
    for (i, c) in rest.char_indices() {
        match c {
            '{' => depth += 1,
            '}' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(&rest[start..i]);
                start = i + 1;
            }
            _ => {}
        }
    }
    parts.push(&rest[start..]);
    parts.into_iter().filter(|p| !p.is_empty()).flat_map(expand).map(|p| format!("{prefix}{p}")).collect()
}

/// Every `crate::` / `super::` path in `code`, as its segments.
fn paths(code: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    // use statements, braces expanded
    let mut rest = code;
    while let Some(i) = rest.find("use ") {
        let before_ok = i == 0 || !rest.as_bytes()[i - 1].is_ascii_alphanumeric() && rest.as_bytes()[i - 1] != b'_';
        let Some(end) = rest[i..].find(';') else { break };
        if before_ok {
            out.extend(expand(&rest[i + 4..i + end]).into_iter().map(|p| split(&p)));
        }
        rest = &rest[i + 4..];
    }
    // inline paths
    let b = code.as_bytes();
    for root in ["crate::", "super::"] {
        for (i, _) in code.match_indices(root) {
            if i > 0 && (b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'_' || b[i - 1] == b':') {
                continue;
            }
            let len = code[i..].find(|c: char| !(c.is_ascii_alphanumeric() || c == '_' || c == ':')).unwrap_or(0);
            out.push(split(&code[i..i + len]));
        }
    }
    // a bare `super::` / `crate::` (the start of a brace group) names nothing
    out.retain(|p| p.len() > 1 && matches!(p.first().map(String::as_str), Some("crate" | "super")));
    out
}

fn split(path: &str) -> Vec<String> {
    path.split("::")
        .filter(|s| !s.is_empty() && *s != "self" && *s != "*")
        .map(|s| s.trim_start_matches("r#").into())
        .collect()
}

/// The module a path names: the longest prefix that is a module of the crate, a parent's
/// re-export followed to its child.
fn resolve(
    from: &Module,
    path: &[String],
    modules: &BTreeSet<Module>,
    reexports: &BTreeMap<(Module, String), String>,
) -> Module {
    let mut at: Module = Vec::new();
    let mut segs = path.iter().peekable();
    if segs.peek().is_some_and(|s| *s == "crate") {
        segs.next();
    } else {
        at = from.clone();
        while segs.peek().is_some_and(|s| *s == "super") {
            segs.next();
            at.pop();
        }
    }
    for s in segs {
        let mut next = at.clone();
        next.push(s.clone());
        if modules.contains(&next) {
            at = next;
        } else if let Some(child) = reexports.get(&(at.clone(), s.clone())) {
            at.push(child.clone());
        } else {
            break;
        }
    }
    at
}

#[test]
fn no_module_reaches_back_to_a_sibling_that_reaches_it() {
    let mut circles = Vec::new();
    let mut edges_seen = 0;
    let mut bins = 0;
    for krate in crates() {
        bins += krate.contains("/bin/") as usize;
        let src = repo().join(&krate);
        let mut files = Vec::new();
        rust_files(&src, &mut files);
        let texts: Vec<(Module, String)> = files
            .iter()
            .map(|f| (module_of(&src, f), code(&std::fs::read_to_string(f).expect("a readable source"))))
            .collect();
        let modules: BTreeSet<Module> = texts.iter().map(|(m, _)| m.clone()).collect();
        // `pub use child::...::{A, B}` in a parent: A and B lead to the child
        let mut reexports = BTreeMap::new();
        for (m, text) in &texts {
            for line in text.lines().map(str::trim_start).filter(|l| l.starts_with("pub use ")) {
                let stmt = line.trim_start_matches("pub use ").trim_end_matches(';');
                for p in expand(stmt).iter().map(|p| split(p)) {
                    let mut child = m.clone();
                    child.push(p[0].clone());
                    if p.len() > 1 && modules.contains(&child) {
                        reexports.insert((m.clone(), p[p.len() - 1].clone()), p[0].clone());
                    }
                }
            }
        }
        // sibling edges: the children of the two modules' common ancestor
        let mut graph: BTreeMap<Module, BTreeSet<Module>> = BTreeMap::new();
        for (m, text) in &texts {
            for p in paths(text) {
                let t = resolve(m, &p, &modules, &reexports);
                let common = m.iter().zip(&t).take_while(|(a, b)| a == b).count();
                if common < m.len() && common < t.len() {
                    graph.entry(m[..=common].to_vec()).or_default().insert(t[..=common].to_vec());
                    edges_seen += 1;
                }
            }
        }
        for start in graph.keys() {
            if let Some(circle) = circle_from(start, &graph) {
                let names: Vec<String> = circle.iter().map(|m| m.join("::")).collect();
                circles.push(format!("{krate}: {}", names.join(" -> ")));
            }
        }
    }
    assert!(bins > 0, "no binary of several files found under a crate's bin/");
    assert!(edges_seen > 100, "only {edges_seen} edges between modules read: is the scanner reading the sources?");
    assert!(circles.is_empty(), "modules that reach back to themselves:\n{}", circles.join("\n"));
}

/// A path from `start` back to itself, if there is one (depth-first).
fn circle_from(start: &Module, graph: &BTreeMap<Module, BTreeSet<Module>>) -> Option<Vec<Module>> {
    let mut stack = vec![(start.clone(), vec![start.clone()])];
    let mut seen = BTreeSet::new();
    while let Some((at, path)) = stack.pop() {
        for next in graph.get(&at).into_iter().flatten() {
            if next == start {
                let mut p = path.clone();
                p.push(start.clone());
                return Some(p);
            }
            if seen.insert(next.clone()) {
                let mut p = path.clone();
                p.push(next.clone());
                stack.push((next.clone(), p));
            }
        }
    }
    None
}

#[test]
fn the_scanner_expands_use_groups_and_follows_reexports() {
    assert_eq!(expand("a::{b, c::{d, e}}"), ["a::b", "a::c::d", "a::c::e"]);
    let modules: BTreeSet<Module> = [vec![], vec!["lang".into()], vec!["lang".into(), "field".into()]].into();
    let mut re = BTreeMap::new();
    re.insert((vec!["lang".to_string()], "Encoder".to_string()), "field".to_string());
    let from = vec!["lang".to_string(), "mix".to_string()];
    let p = paths("use super::{Encoder, field::x};\nlet y = crate::lang::field::f();");
    let got: Vec<Module> = p.iter().map(|p| resolve(&from, p, &modules, &re)).collect();
    let field = vec!["lang".to_string(), "field".to_string()];
    assert_eq!(got, [field.clone(), field.clone(), field]);
    // comments and doc-only imports left out (a use statement is also read as an inline path)
    let read: BTreeSet<Vec<String>> =
        paths(&code("// use crate::a;\n#[cfg(doc)]\nuse crate::b;\nuse crate::c;\n")).into_iter().collect();
    assert_eq!(read, BTreeSet::from([vec!["crate".to_string(), "c".to_string()]]));
}
