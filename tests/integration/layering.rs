//! The library's modules form layers (camera models → kernel offsets → the deformable-conv op →
//! nn → data → training / evaluation → experiments → reports): no top-level module may depend on
//! one that depends back on it. Read from the sources (`crate::NAME` in code; comments, doc links
//! and tests left out), so a new import that closes a cycle fails here, naming the cycle and a
//! file on each of its edges.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The binary's files (they may use anything) and the crate root (it declares the modules).
const OUTSIDE: [&str; 4] = ["main.rs", "cli.rs", "commands", "lib.rs"];

/// `from -> to -> a file of `from` that names `to``.
type Graph = BTreeMap<String, BTreeMap<String, PathBuf>>;

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The code of a file without its tests (everything from the first `#[cfg(test)]`, the
/// convention of this tree) and without comments.
fn code(text: &str) -> String {
    let text = text.split("#[cfg(test)]").next().unwrap_or("");
    text.lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n")
}

fn ident(s: &str) -> &str {
    let end = s
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(s.len());
    &s[..end]
}

/// The top-level modules a piece of code names as `crate::NAME` or `crate::{NAME, ...}`.
fn named_modules(code: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    for (i, _) in code.match_indices("crate::") {
        let rest = &code[i + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            // Path heads at the group's top level: after `{` and after each `,`.
            let (mut depth, mut head) = (1, true);
            for (j, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' => {
                        depth -= 1;
                        if depth == 0 {
                            break;
                        }
                    }
                    ',' if depth == 1 => head = true,
                    c if head && depth == 1 && !c.is_whitespace() => {
                        head = false;
                        let name = ident(&group[j..]);
                        if !name.is_empty() {
                            found.insert(name.to_string());
                        }
                    }
                    _ => {}
                }
            }
        } else {
            let name = ident(rest);
            if !name.is_empty() {
                found.insert(name.to_string());
            }
        }
    }
    found
}

fn graph(src: &Path) -> Graph {
    let mut paths = Vec::new();
    rust_files(src, &mut paths);
    paths.sort();
    // (path within src, its top-level module), the binary's files left out.
    let files: Vec<(PathBuf, String)> = paths
        .iter()
        .map(|f| f.strip_prefix(src).unwrap().to_path_buf())
        .filter(|rel| {
            let first = rel.components().next().unwrap().as_os_str();
            !OUTSIDE.contains(&first.to_string_lossy().as_ref())
        })
        .map(|rel| {
            let module = top_module(&rel);
            (rel, module)
        })
        .collect();
    let modules: BTreeSet<&String> = files.iter().map(|(_, m)| m).collect();
    let mut g = Graph::new();
    for (rel, from) in &files {
        if rel.file_name().is_some_and(|n| n == "tests.rs") {
            continue;
        }
        let text = std::fs::read_to_string(src.join(rel)).unwrap();
        for to in named_modules(&code(&text)) {
            if &to != from && modules.contains(&to) {
                g.entry(from.clone())
                    .or_default()
                    .entry(to)
                    .or_insert_with(|| rel.clone());
            }
        }
    }
    g
}

/// `ops/plan.rs` -> `ops`, `io.rs` -> `io` (a path within src).
fn top_module(rel: &Path) -> String {
    let first = rel
        .components()
        .next()
        .unwrap()
        .as_os_str()
        .to_string_lossy();
    first.strip_suffix(".rs").unwrap_or(&first).to_string()
}

/// A cycle of the graph (as the list of its modules, the first repeated at the end), if any.
fn find_cycle(g: &Graph) -> Option<Vec<String>> {
    fn visit(
        g: &Graph,
        m: &str,
        state: &mut BTreeMap<String, u8>,
        path: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(m.to_string(), 1);
        path.push(m.to_string());
        for next in g.get(m).into_iter().flat_map(|e| e.keys()) {
            match state.get(next).copied().unwrap_or(0) {
                1 => {
                    let start = path.iter().position(|p| p == next).unwrap();
                    let mut cycle = path[start..].to_vec();
                    cycle.push(next.clone());
                    return Some(cycle);
                }
                0 => {
                    if let Some(c) = visit(g, next, state, path) {
                        return Some(c);
                    }
                }
                _ => {}
            }
        }
        path.pop();
        state.insert(m.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for m in g.keys() {
        if state.get(m).copied().unwrap_or(0) == 0 {
            if let Some(c) = visit(g, m, &mut state, &mut Vec::new()) {
                return Some(c);
            }
        }
    }
    None
}

#[test]
fn the_library_modules_have_no_import_cycles() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let g = graph(&src);
    // The scan sees the layers it should: the op above the offsets, the reports above the runs.
    assert!(g["ops"].contains_key("kernel"), "{g:#?}");
    assert!(g["report"].contains_key("experiment"), "{g:#?}");
    if let Some(cycle) = find_cycle(&g) {
        let edges: Vec<String> = cycle
            .windows(2)
            .map(|w| format!("{} -> {} ({})", w[0], w[1], g[&w[0]][&w[1]].display()))
            .collect();
        panic!("import cycle: {}", edges.join(", "));
    }
}

#[test]
fn the_scan_reads_paths_groups_and_skips_comments_and_tests() {
    let text = "use crate::ops::plan;\nuse crate::{data::Batch, io,\n  nn::{Head, unet}};\n\
                // crate::report in a comment\nfn f() { crate::util::fmt_f64(1.0); }\n\
                #[cfg(test)]\nmod tests { use crate::experiment; }\n";
    let names: Vec<String> = named_modules(&code(text)).into_iter().collect();
    assert_eq!(names, ["data", "io", "nn", "ops", "util"]);
    let mut g = Graph::new();
    for (a, b) in [("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")] {
        g.entry(a.into())
            .or_default()
            .insert(b.into(), PathBuf::from(a));
    }
    assert_eq!(find_cycle(&g).unwrap(), ["a", "b", "c", "a"]);
    g.get_mut("c").unwrap().remove("a");
    assert_eq!(find_cycle(&g), None);
}
