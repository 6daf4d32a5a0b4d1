//! The architecture's layering, checked on the source: no import cycle between the files of the
//! server's crates, and no HTTP crate in the core. A cycle is how domain code ended up returning
//! HTTP errors before; this test keeps it from coming back.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Module path (`machine::actor`) -> source, for every `.rs` file under `src`.
fn modules(src: &Path) -> BTreeMap<String, String> {
    fn walk(dir: &Path, root: &Path, out: &mut BTreeMap<String, String>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, root, out);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let rel = p.strip_prefix(root).unwrap().with_extension("");
                let mut m = rel.to_string_lossy().replace('/', "::");
                if let Some(parent) = m.strip_suffix("::mod") {
                    m = parent.to_string();
                }
                if m == "lib" || m == "main" {
                    m = String::new();
                }
                out.insert(m, std::fs::read_to_string(&p).unwrap());
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(src, src, &mut out);
    out
}

/// Edges file -> file from `crate::a::b` paths (the longest prefix that is a module), test
/// modules left out.
fn graph(mods: &BTreeMap<String, String>) -> BTreeMap<String, BTreeSet<String>> {
    let mut g = BTreeMap::new();
    for (m, src) in mods {
        let src = src.split("#[cfg(test)]\nmod tests").next().unwrap_or(src);
        let mut deps = BTreeSet::new();
        for (i, _) in src.match_indices("crate::") {
            let path: String = src[i + 7..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_' || *c == ':')
                .collect();
            let mut parts: Vec<&str> = path.split("::").filter(|p| !p.is_empty()).collect();
            while !parts.is_empty() {
                let t = parts.join("::");
                if mods.contains_key(&t) {
                    // A module and its own parent or child count as one: their edges are inside.
                    if !same_unit(&t, m) {
                        deps.insert(t);
                    }
                    break;
                }
                parts.pop();
            }
        }
        g.insert(m.clone(), deps);
    }
    g
}

/// Whether `a` and `b` are the same module, or one is the other's ancestor (`machine` and
/// `machine::actor`).
fn same_unit(a: &str, b: &str) -> bool {
    let inside = |child: &str, parent: &str| {
        child == parent
            || child
                .strip_prefix(parent)
                .is_some_and(|r| r.starts_with("::"))
    };
    inside(a, b) || inside(b, a)
}

fn cycle(g: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    // Depth-first search with colours; returns the first cycle found.
    fn visit(
        v: &str,
        g: &BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(v.to_string(), 1);
        stack.push(v.to_string());
        for w in g.get(v).into_iter().flatten() {
            match state.get(w).copied().unwrap_or(0) {
                0 => {
                    if let Some(c) = visit(w, g, state, stack) {
                        return Some(c);
                    }
                }
                1 => {
                    let at = stack.iter().position(|s| s == w).unwrap_or(0);
                    let mut c = stack[at..].to_vec();
                    c.push(w.clone());
                    return Some(c);
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(v.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for v in g.keys() {
        if state.get(v).copied().unwrap_or(0) == 0 {
            if let Some(c) = visit(v, g, &mut state, &mut Vec::new()) {
                return Some(c);
            }
        }
    }
    None
}

#[test]
fn no_import_cycle_between_files_of_the_server_crates() {
    let server = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
    for krate in ["core/src", "http/src", "integrations/src", "src"] {
        let g = graph(&modules(&server.join(krate)));
        assert!(g.len() > 2, "{krate}: no modules found");
        if let Some(c) = cycle(&g) {
            panic!("import cycle in server/{krate}: {}", c.join(" -> "));
        }
    }
}

#[test]
fn the_checker_sees_a_cycle_when_there_is_one() {
    let mut mods = BTreeMap::new();
    mods.insert("a".to_string(), "use crate::b::Thing;".to_string());
    mods.insert("b".to_string(), "fn f(_: crate::a::X) {}".to_string());
    mods.insert("c".to_string(), "use crate::a;".to_string());
    assert!(cycle(&graph(&mods)).is_some());
    mods.insert("b".to_string(), String::new());
    assert!(cycle(&graph(&mods)).is_none());
    // A parent and its child may use each other; a cycle through a third module still counts.
    mods.insert("m".to_string(), "use crate::m::child::X;".to_string());
    mods.insert("m::child".to_string(), "use crate::m::Y;".to_string());
    assert!(cycle(&graph(&mods)).is_none());
    mods.insert(
        "m::child".to_string(),
        "use crate::m::Y; use crate::c;".to_string(),
    );
    mods.insert("a".to_string(), "use crate::m::child::X;".to_string());
    mods.insert("b".to_string(), String::new());
    mods.insert("c".to_string(), "use crate::a;".to_string());
    assert!(cycle(&graph(&mods)).is_some());
}

#[test]
fn the_core_does_not_depend_on_http() {
    let manifest =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("Cargo.toml")).unwrap();
    for http in ["axum", "tower", "hyper", "reqwest"] {
        assert!(
            !manifest.lines().any(|l| l.trim_start().starts_with(http)),
            "fresa-core depends on {http}: the core must not know HTTP"
        );
    }
}
