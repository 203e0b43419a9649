//! The layering docs/architecture.md promises, checked against the code, so it
//! cannot regrow unnoticed: each workspace crate depends only on the crates its
//! row of the layer table names, every crate has a row, and no two modules of a
//! crate (or of the binary) import each other, directly or round a circle.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The workspace's library crates, from the root Cargo.toml's `members`.
fn members() -> Vec<String> {
    let manifest = read(&root().join("Cargo.toml"));
    let line = manifest.lines().find(|l| l.trim_start().starts_with("members")).expect("the root Cargo.toml lists its members");
    quoted(line)
}

fn quoted(s: &str) -> Vec<String> {
    s.split('"').skip(1).step_by(2).map(String::from).collect()
}

fn backticked(s: &str) -> Vec<String> {
    s.split('`').skip(1).step_by(2).map(String::from).collect()
}

/// The layer table: each crate's row and the workspace crates its "uses" column names.
fn layer_table(members: &[String]) -> BTreeMap<String, BTreeSet<String>> {
    let doc = read(&root().join("docs/architecture.md"));
    let section = doc.split("### Layers").nth(1).expect("docs/architecture.md has a \"Layers\" section");
    let rows = section.lines().skip_while(|l| !l.starts_with('|')).take_while(|l| l.starts_with('|'));
    let mut table = BTreeMap::new();
    for row in rows {
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        let Some(name) = cells.get(1).and_then(|c| backticked(c).into_iter().next()) else { continue };
        if members.contains(&name) {
            let uses = cells.get(2).map_or(Vec::new(), |c| backticked(c));
            table.insert(name, uses.into_iter().filter(|u| members.contains(u)).collect());
        }
    }
    table
}

/// The workspace crates a crate's `[dependencies]` name (path dependencies).
fn workspace_dependencies(krate: &str, members: &[String]) -> BTreeSet<String> {
    let manifest = read(&root().join(krate).join("Cargo.toml"));
    let mut in_dependencies = false;
    let mut found = BTreeSet::new();
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_dependencies = line == "[dependencies]";
            continue;
        }
        if in_dependencies && line.contains("path") {
            let name = line.split(['=', '.', ' ']).next().unwrap_or_default().to_string();
            if members.contains(&name) {
                found.insert(name);
            }
        }
    }
    found
}

/// The modules of one source folder (its top-level files and folders, and the crate root
/// `lib` or `main`) and the other top-level modules each one names: through `crate::`,
/// through `super::` chains that climb to the root, and, in the root, as `module::`. A name
/// the root re-exports (`pub use module::Name`) counts as its module's, so only items the
/// root itself defines make a module depend on the root.
fn module_imports(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let relative = |p: &Path| p.strip_prefix(src).unwrap().with_extension("");
    let top = |p: &Path| relative(p).components().next().unwrap().as_os_str().to_string_lossy().to_string();
    let mut files = Vec::new();
    let mut stack = vec![src.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|e| e == "rs") {
                files.push(path);
            }
        }
    }
    let root_name = if src.join("lib.rs").exists() { "lib" } else { "main" };
    let modules: BTreeSet<String> = files.iter().map(|f| top(f)).collect();
    let reexported = reexports(&read(&src.join(format!("{root_name}.rs"))), &modules);
    let owner = |name: &str| if modules.contains(name) && name != root_name { name.to_string() } else { reexported.get(name).cloned().unwrap_or(root_name.to_string()) };
    let mut imports: BTreeMap<String, BTreeSet<String>> = modules.iter().map(|m| (m.clone(), BTreeSet::new())).collect();
    for file in &files {
        let from = top(file);
        let rel = relative(file);
        // How deep the file's module sits: the root 0, src/x.rs and src/x/mod.rs 1, src/x/y.rs 2.
        let depth = if from == root_name { 0 } else { rel.components().count() - usize::from(rel.ends_with("mod")) };
        for line in read(file).lines() {
            let code = line.find("//").filter(|&i| i == 0 || line[..i].ends_with(' ')).map_or(line, |i| &line[..i]);
            let mut named = names_after(code, "crate::");
            named.extend(names_after_super(code, depth));
            // A root's `pub use` re-exports: the names count as their modules' (above), not as the root's own use.
            if from == root_name && !code.trim_start().starts_with("pub use") {
                named.extend(paths_from_root(code).into_iter().filter(|n| modules.contains(n)));
            }
            for name in named.iter().filter(|n| !n.is_empty()) {
                let to = owner(name);
                if to != from {
                    imports.get_mut(&from).unwrap().insert(to);
                }
            }
        }
    }
    imports
}

/// `use module::{A, B}` and `pub use module::A` lines of a crate root (what `crate::A`
/// reaches from anywhere in the crate): name -> module.
fn reexports(root: &str, modules: &BTreeSet<String>) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    for line in root.lines().map(str::trim).filter(|l| l.starts_with("pub use ") || l.starts_with("use ")) {
        let path = line.trim_start_matches("pub ").trim_start_matches("use ").trim_start_matches("crate::").trim_end_matches(';');
        let Some((module, rest)) = path.split_once("::") else { continue };
        if modules.contains(module) {
            for name in names_after(&format!("x::{rest}"), "x::") {
                out.insert(name, module.to_string());
            }
        }
    }
    out
}

/// What `crate::x` and `use crate::{x, y::z}` name first, in one line of code.
fn names_after_crate(code: &str) -> Vec<String> {
    names_after(code, "crate::")
}

/// The first names after each `prefix` in a line: `prefix x` and `prefix {x, y::z}`.
fn names_after(code: &str, prefix: &str) -> Vec<String> {
    let ident = |s: &str| s.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect::<String>();
    let mut names = Vec::new();
    for (i, _) in code.match_indices(prefix) {
        if prefix == "super::" && code[..i].ends_with("super::") {
            continue;
        }
        let rest = &code[i + prefix.len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let group = &group[..group.find('}').unwrap_or(group.len())];
            names.extend(group.split(',').map(|item| ident(item.trim())));
        } else {
            names.push(ident(rest));
        }
    }
    names
}

/// The names `super::` chains reach at the crate root from a module `depth` deep.
fn names_after_super(code: &str, depth: usize) -> Vec<String> {
    let mut names = Vec::new();
    for (i, _) in code.match_indices("super::") {
        if code[..i].ends_with("super::") {
            continue; // counted from the chain's first `super::`
        }
        let (mut climbs, mut rest) = (0, &code[i..]);
        while let Some(after) = rest.strip_prefix("super::") {
            climbs += 1;
            rest = after;
        }
        if climbs == depth {
            names.extend(names_after(&format!("x::{rest}"), "x::").into_iter().take(if rest.starts_with('{') { usize::MAX } else { 1 }));
        }
    }
    names
}

/// The crate root's own paths that start with a name: `name::...` not after another `::`.
fn paths_from_root(code: &str) -> Vec<String> {
    let mut names = Vec::new();
    for (i, _) in code.match_indices("::") {
        let before = &code[..i];
        let start = before.rfind(|c: char| !(c.is_alphanumeric() || c == '_')).map_or(0, |j| j + 1);
        if start == 0 || !before[..start].ends_with("::") {
            names.push(before[start..].to_string());
        }
    }
    names
}

/// A circle of imports, if there is one: the modules round it.
fn circle(imports: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(at: &str, imports: &BTreeMap<String, BTreeSet<String>>, path: &mut Vec<String>, done: &mut BTreeSet<String>) -> Option<Vec<String>> {
        if let Some(start) = path.iter().position(|m| m == at) {
            let mut round = path[start..].to_vec();
            round.push(at.to_string());
            return Some(round);
        }
        if done.contains(at) {
            return None;
        }
        path.push(at.to_string());
        for next in &imports[at] {
            if let Some(round) = visit(next, imports, path, done) {
                return Some(round);
            }
        }
        path.pop();
        done.insert(at.to_string());
        None
    }
    let mut done = BTreeSet::new();
    imports.keys().find_map(|m| visit(m, imports, &mut Vec::new(), &mut done))
}

#[test]
fn every_crate_depends_only_on_what_its_layer_allows() {
    let members = members();
    assert!(members.len() >= 8, "members: {members:?}");
    let table = layer_table(&members);
    for krate in &members {
        let allowed = table.get(krate).unwrap_or_else(|| panic!("docs/architecture.md's layer table has no row for `{krate}`"));
        let used = workspace_dependencies(krate, &members);
        let extra: Vec<&String> = used.difference(allowed).collect();
        assert!(extra.is_empty(), "`{krate}` depends on {extra:?}, which its row of the layer table (docs/architecture.md) does not allow");
    }
    // The ground floor stays the ground floor.
    assert!(table["memory"].is_empty(), "memory's row names workspace crates: {:?}", table["memory"]);
}

#[test]
fn no_two_modules_import_each_other() {
    let mut sources: Vec<PathBuf> = members().iter().map(|m| root().join(m).join("src")).collect();
    sources.push(root().join("src"));
    let mut modules = 0;
    for src in sources {
        let imports = module_imports(&src);
        modules += imports.len();
        if let Some(round) = circle(&imports) {
            panic!("{}: the modules import round a circle: {}", src.display(), round.join(" -> "));
        }
    }
    assert!(modules > 50, "found only {modules} modules: the scan is looking in the wrong places");
}

#[test]
fn the_checks_see_a_circle_and_a_forbidden_dependency() {
    // The scanner on code it must catch, so the two tests above cannot pass by seeing nothing.
    assert_eq!(names_after_crate("use crate::{graph::Tensor, error::ModelError};"), ["graph", "error"]);
    assert_eq!(names_after_crate("let x = crate::manifest::load(p);"), ["manifest"]);
    assert_eq!(names_after_super("use super::super::{engine, Config};", 2), ["engine", "Config"]);
    assert!(names_after_super("use super::St;", 2).is_empty(), "one level up from depth 2 is not the root");
    assert_eq!(paths_from_root("let m = predict::run(model::x);"), ["predict", "model"]);
    let modules: BTreeSet<String> = ["overlap", "lib"].map(String::from).into();
    assert_eq!(reexports("pub use overlap::{Frustum, overlap_score};", &modules)["Frustum"], "overlap");
    let imports: BTreeMap<String, BTreeSet<String>> = [("graph", vec!["manifest"]), ("manifest", vec!["graph"]), ("error", vec![])]
        .into_iter()
        .map(|(m, to)| (m.to_string(), to.into_iter().map(String::from).collect()))
        .collect();
    assert_eq!(circle(&imports), Some(vec!["graph".to_string(), "manifest".into(), "graph".into()]));
    let members = members();
    let table = layer_table(&members);
    assert!(!table["model"].contains("api"), "model may not use api: {:?}", table["model"]);
    assert!(workspace_dependencies("api", &members).contains("model"), "api's Cargo.toml names model as a path dependency");
}
