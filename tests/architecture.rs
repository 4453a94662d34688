//! The layout keeps its shape: no import circle between files of `src/`, the LOD core
//! free of Vulkan, and each layer using only the ones below it (`src/lib.rs` lists them).
//! Each check is also run on a copy of `src/` with one line added that breaks it, and
//! must fail there.

mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A module's path (`lod::traversal`; `` for lib.rs) for each file under `root`.
fn modules(root: &Path) -> BTreeMap<String, PathBuf> {
    fn walk(dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    let mut files = Vec::new();
    walk(root, &mut files);
    let mut out = BTreeMap::new();
    for f in files {
        let rel = f.strip_prefix(root).unwrap().with_extension("");
        let mut parts: Vec<String> = rel.iter().map(|c| c.to_string_lossy().into_owned()).collect();
        if parts.last().is_some_and(|l| l == "mod" || l == "lib") {
            parts.pop();
        }
        if parts.len() == 1 && parts[0] == "main" {
            continue; // the binary: a crate of its own, which uses the library
        }
        out.insert(parts.join("::"), f);
    }
    out
}

/// The source without comments and string literals (what the compiler reads as code).
fn code(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        if b[i..].starts_with(b"//") {
            while i < b.len() && b[i] != b'\n' {
                i += 1;
            }
        } else if b[i..].starts_with(b"/*") {
            let mut depth = 0;
            while i < b.len() {
                if b[i..].starts_with(b"/*") {
                    depth += 1;
                    i += 2;
                } else if b[i..].starts_with(b"*/") {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    i += 1;
                }
            }
        } else if b[i] == b'"' || (b[i] == b'r' && i + 1 < b.len() && (b[i + 1] == b'"' || b[i + 1] == b'#')) {
            // A (raw) string literal: skipped whole.
            let raw = b[i] == b'r';
            if raw {
                i += 1;
            }
            let mut hashes = 0;
            while raw && i < b.len() && b[i] == b'#' {
                hashes += 1;
                i += 1;
            }
            if i >= b.len() || b[i] != b'"' {
                out.push('r');
                continue; // an identifier starting with r
            }
            i += 1;
            while i < b.len() {
                if !raw && b[i] == b'\\' {
                    i += 2;
                } else if b[i] == b'"' && b[i + 1..].iter().take(hashes).filter(|&&c| c == b'#').count() == hashes {
                    i += 1 + hashes;
                    break;
                } else {
                    i += 1;
                }
            }
            out.push_str("\"\"");
        } else if b[i] == b'\'' && i + 2 < b.len() && (b[i + 2] == b'\'' || b[i + 1] == b'\\') {
            // A character literal ('"' would otherwise open a string).
            i += 1;
            while i < b.len() && b[i] != b'\'' {
                i += if b[i] == b'\\' { 2 } else { 1 };
            }
            i += 1;
            out.push_str("' '");
        } else {
            out.push(b[i] as char);
            i += 1;
        }
    }
    out
}

/// Paths in `code` that start with one of `roots` (`crate`, `super`, `self`, a child
/// module's name), as the words after it: `crate::lod::block::X` gives `[lod, block, X]`.
/// A `{...}` group after `::` gives one path per item.
fn paths_from(code: &str, root: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let bytes = code.as_bytes();
    let word = |c: u8| c.is_ascii_alphanumeric() || c == b'_';
    let needle = format!("{root}::");
    let mut start = 0;
    while let Some(found) = code[start..].find(&needle) {
        let at = start + found;
        start = at + needle.len();
        if at > 0 && (word(bytes[at - 1]) || bytes[at - 1] == b':') {
            continue; // part of a longer path or name
        }
        expand(&code[start..], Vec::new(), &mut out);
    }
    out
}

/// Reads `a::b::{c, d::e}` from the start of `s` onto `prefix`.
fn expand(s: &str, prefix: Vec<String>, out: &mut Vec<Vec<String>>) {
    let s = s.trim_start();
    if let Some(rest) = s.strip_prefix('{') {
        let mut depth = 0;
        let mut item = String::new();
        for c in rest.chars() {
            match c {
                '{' => depth += 1,
                '}' if depth == 0 => break,
                '}' => depth -= 1,
                ',' if depth == 0 => {
                    expand(&item, prefix.clone(), out);
                    item.clear();
                    continue;
                }
                _ => {}
            }
            item.push(c);
        }
        expand(&item, prefix, out);
        return;
    }
    let name: String = s.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
    if name.is_empty() {
        if !prefix.is_empty() {
            out.push(prefix);
        }
        return;
    }
    let mut p = prefix;
    p.push(name.clone());
    let rest = &s[name.len()..];
    match rest.strip_prefix("::") {
        Some(r) => expand(r, p, out),
        None => out.push(p),
    }
}

/// Which files each file uses: every path through `crate::`, `super::` or `self::`, or
/// through a child module declared in the file, resolved to the longest module that is a
/// file. A facade's `pub use child::X` is a use of the child like any other, so a child
/// that imports through its parent's re-exports makes a circle.
fn graph(root: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let mods = modules(root);
    let mut edges = BTreeMap::new();
    for (m, file) in &mods {
        let text = code(&std::fs::read_to_string(file).unwrap());
        let here: Vec<String> = if m.is_empty() { Vec::new() } else { m.split("::").map(String::from).collect() };
        let is_dir_module = file.ends_with("mod.rs") || file.ends_with("lib.rs");
        // `self` and child names resolve from the module itself; `super` from its parent.
        let mut absolute: Vec<Vec<String>> = paths_from(&text, "crate");
        for p in paths_from(&text, "self") {
            absolute.push(here.iter().cloned().chain(p).collect());
        }
        for p in paths_from(&text, "super") {
            let mut base = here.clone();
            base.pop();
            absolute.push(base.into_iter().chain(p).collect());
        }
        let children: Vec<String> = mods
            .keys()
            .filter_map(|k| {
                let rest = if here.is_empty() { Some(k.as_str()) } else { k.strip_prefix(&format!("{m}::")) };
                rest.filter(|r| !r.is_empty() && !r.contains("::")).map(String::from)
            })
            .collect();
        if is_dir_module {
            for c in &children {
                for p in paths_from(&text, c) {
                    absolute.push(here.iter().cloned().chain(std::iter::once(c.clone())).chain(p).collect());
                }
            }
        }
        let mut uses = BTreeSet::new();
        for p in absolute {
            let target = (0..=p.len()).rev().map(|n| p[..n].join("::")).find(|c| mods.contains_key(c));
            if let Some(t) = target {
                if t != *m && !t.is_empty() {
                    uses.insert(t);
                }
            }
        }
        edges.insert(m.clone(), uses);
    }
    edges
}

/// Every import circle, as the files on it in order.
fn circles(edges: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    // Tarjan's strongly connected components; a component of more than one file holds a
    // circle, which is then walked out explicitly for the message.
    struct State<'a> {
        edges: &'a BTreeMap<String, BTreeSet<String>>,
        index: BTreeMap<&'a str, usize>,
        low: BTreeMap<&'a str, usize>,
        stack: Vec<&'a str>,
        on: BTreeSet<&'a str>,
        out: Vec<Vec<String>>,
    }
    fn visit<'a>(s: &mut State<'a>, v: &'a str) {
        let n = s.index.len();
        s.index.insert(v, n);
        s.low.insert(v, n);
        s.stack.push(v);
        s.on.insert(v);
        for w in s.edges.get(v).into_iter().flatten() {
            let w = w.as_str();
            if !s.index.contains_key(w) {
                visit(s, w);
                let lw = s.low[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(lw);
            } else if s.on.contains(w) {
                let iw = s.index[w];
                let lv = s.low.get_mut(v).unwrap();
                *lv = (*lv).min(iw);
            }
        }
        if s.low[v] == s.index[v] {
            let mut comp = Vec::new();
            while let Some(w) = s.stack.pop() {
                s.on.remove(w);
                comp.push(w.to_string());
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                s.out.push(comp);
            }
        }
    }
    let mut s = State {
        edges,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in edges.keys() {
        if !s.index.contains_key(v.as_str()) {
            visit(&mut s, v);
        }
    }
    s.out
}

/// Files of the LOD core that name `ash` or the crate's Vulkan layer.
fn vulkan_in_core(root: &Path) -> Vec<String> {
    let mut found = Vec::new();
    for (m, file) in modules(root) {
        if !(m == "lod" || m.starts_with("lod::")) {
            continue;
        }
        let text = code(&std::fs::read_to_string(&file).unwrap());
        let names_ash = !paths_from(&text, "ash").is_empty() || text.contains("extern crate ash");
        let names_vk = paths_from(&text, "crate").iter().any(|p| p.first().is_some_and(|f| f == "vk"));
        if names_ash || names_vk {
            found.push(m);
        }
    }
    found
}

/// The layers of `src/lib.rs`, lowest first; a file may use its own layer and those below.
const LAYERS: [&str; 10] = ["vk", "lod", "input", "prepare", "stream", "trace", "gpu", "errors", "draw", "app"];

/// Uses of a higher layer, and uses of the audit (a test oracle) from anything on the
/// rendering path (`lod`, `gpu`, `errors`, `draw`).
fn layer_breaks(edges: &BTreeMap<String, BTreeSet<String>>) -> Vec<String> {
    let layer = |m: &str| LAYERS.iter().position(|l| m == *l || m.starts_with(&format!("{l}::")));
    let mut out = Vec::new();
    for (from, uses) in edges {
        let Some(lf) = layer(from) else { continue };
        for to in uses {
            if layer(to).is_some_and(|lt| lt > lf) {
                out.push(format!("{from} uses {to} (a higher layer)"));
            }
            let rendering = ["lod", "gpu", "errors", "draw"].contains(&LAYERS[lf]);
            if to == "lod::audit" && rendering && from != "lod" {
                out.push(format!("{from} uses the audit, an oracle nothing on the rendering path may depend on"));
            }
        }
    }
    out
}

fn src() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("src")
}

/// A copy of `src/` with `line` added at the top of `file`.
fn mutated(dir: &Path, file: &str, line: &str) -> PathBuf {
    fn copy(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let p = e.unwrap().path();
            let dest = to.join(p.file_name().unwrap());
            if p.is_dir() {
                copy(&p, &dest);
            } else {
                std::fs::copy(&p, &dest).unwrap();
            }
        }
    }
    let root = dir.join("src");
    copy(&src(), &root);
    let f = root.join(file);
    let text = std::fs::read_to_string(&f).unwrap();
    std::fs::write(&f, format!("{line}\n{text}")).unwrap();
    root
}

#[test]
fn no_import_circle_between_files() {
    let edges = graph(&src());
    assert!(edges.len() > 40, "only {} files found under src/", edges.len());
    // The reader understood the tree: known uses are seen, through each kind of path.
    for (from, to) in [
        ("lod::traversal", "lod::morph"), // crate::lod::morph
        ("vk::command", "vk::device"),    // super::device
        ("vk", "vk::device"),             // pub use device::...
        ("draw::frame", "errors::feed"),
    ] {
        assert!(edges[from].contains(to), "{from} should use {to}: {:?}", edges[from]);
    }
    let found = circles(&edges);
    assert!(found.is_empty(), "import circles between files of src/: {found:?}");
}

#[test]
fn the_lod_core_names_no_vulkan() {
    let core = modules(&src()).keys().filter(|m| m.starts_with("lod::")).count();
    assert!(core >= 10, "only {core} files in src/lod");
    assert_eq!(vulkan_in_core(&src()), Vec::<String>::new());
}

#[test]
fn layers_use_only_those_below() {
    assert_eq!(layer_breaks(&graph(&src())), Vec::<String>::new());
}

/// The checks fail on the mistakes they guard against: one `use` that closes a circle
/// (the heightfield reaching up to the pyramid built from it), one `ash` import in the
/// core, one use of the Vulkan layer from it, a use of the draw thread from the errors
/// activity, and the production bound depending on the audit.
#[test]
fn each_check_fails_on_a_mutation() {
    let tmp = common::TempDir::new("architecture");
    let circle = mutated(&tmp.path().join("a"), "lod/heightfield.rs", "use crate::lod::pyramid::MinMaxPyramid;");
    let found = circles(&graph(&circle));
    assert!(
        found.iter().any(|c| c.contains(&"lod::heightfield".to_string()) && c.contains(&"lod::pyramid".to_string())),
        "the circle was not found: {found:?}"
    );
    let facade = mutated(&tmp.path().join("b"), "vk/device.rs", "use super::Fence;");
    assert!(!circles(&graph(&facade)).is_empty(), "a child importing through its facade makes no circle");
    let ash = mutated(&tmp.path().join("c"), "lod/block.rs", "use ash::vk;");
    assert_eq!(vulkan_in_core(&ash), vec!["lod::block".to_string()]);
    let vk = mutated(&tmp.path().join("d"), "lod/gie.rs", "#[allow(unused_imports)] use crate::vk::{Device as _D};");
    assert_eq!(vulkan_in_core(&vk), vec!["lod::gie".to_string()]);
    let up = mutated(&tmp.path().join("e"), "errors/feed.rs", "use crate::draw::frame::LodChoice;");
    let breaks = layer_breaks(&graph(&up));
    assert!(breaks.iter().any(|b| b.starts_with("errors::feed uses draw::frame")), "{breaks:?}");
    let oracle = mutated(&tmp.path().join("f"), "lod/stitch.rs", "use crate::lod::audit::audit;");
    let breaks = layer_breaks(&graph(&oracle));
    assert!(breaks.iter().any(|b| b.starts_with("lod::stitch uses the audit")), "{breaks:?}");
    // Comments and strings are not code.
    let comment = mutated(&tmp.path().join("g"), "lod/block.rs", "// use ash::vk; \"crate::vk::Device\"");
    assert!(vulkan_in_core(&comment).is_empty());
}

/// The README is short, and its layout table is the tree: every file of `src/` and
/// `tools/` is named in it (a folder's row names its files), and every path it names
/// exists.
#[test]
fn the_readme_layout_table_is_the_tree() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let lines = readme.lines().count();
    assert!(lines <= 210, "README.md has {lines} lines; the rest belongs in docs/");
    let start = readme.find("\n## Layout").expect("a Layout section");
    let table: Vec<&str> = readme[start + 1..].lines().skip(1).take_while(|l| !l.starts_with("## ")).collect();
    let rows: Vec<(String, String)> = table
        .iter()
        .filter_map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let path = cells.get(1)?.strip_prefix('`')?.strip_suffix('`')?;
            Some((path.to_string(), cells.get(2).copied().unwrap_or("").to_string()))
        })
        .collect();
    assert!(rows.len() >= 15, "layout table rows: {rows:?}");
    for (path, _) in &rows {
        assert!(root.join(path).exists(), "README layout names {path}, which does not exist");
    }
    let named = |file: &Path| {
        let rel = file.strip_prefix(&root).unwrap().to_string_lossy().replace('\\', "/");
        let name = file.file_name().unwrap().to_string_lossy();
        rows.iter().any(|(p, what)| {
            *p == rel || (p.ends_with('/') && rel.starts_with(p.as_str()) && what.contains(&format!("`{name}`")))
        })
    };
    let mut missing = Vec::new();
    for dir in ["src", "tools"] {
        let mut files = Vec::new();
        let mut stack = vec![root.join(dir)];
        while let Some(d) = stack.pop() {
            for e in std::fs::read_dir(d).unwrap() {
                let p = e.unwrap().path();
                if p.is_dir() {
                    stack.push(p);
                } else {
                    files.push(p);
                }
            }
        }
        for f in files {
            let facade = f.file_name().is_some_and(|n| n == "mod.rs");
            let listed_as_row = rows.iter().any(|(p, _)| root.join(p) == f);
            if !facade && !listed_as_row && !named(&f) {
                missing.push(f.strip_prefix(&root).unwrap().display().to_string());
            }
        }
    }
    assert!(missing.is_empty(), "files the README's layout table does not name: {missing:?}");
}
