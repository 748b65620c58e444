//! The doors between rooms run one way: the import graph of src/ (its top-level rooms, and the service's modules
//! one by one) has no circle, and each room uses only rooms listed before it in its `# Layout` (src/lib.rs for the
//! rooms, src/service/mod.rs for the service's modules). Read from the source text: `crate::`, `super::` and `self::`
//! paths, `use` trees, and `mod` declarations (a room uses what it declares); test modules count too.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use crate::support::root;

/// The rooms whose modules are nodes of the graph one by one (the others are one node each).
const SPLIT: &[&str] = &["service"];

/// A module's path from the crate root (`["service", "state"]`); empty for the root.
type ModPath = Vec<String>;

#[derive(Debug)]
struct Token {
    text: String,
    line: usize,
}

/// Rust source as tokens: identifiers, `::` and single punctuation; comments, strings, chars and numbers dropped.
fn tokens(src: &str) -> Vec<Token> {
    let c: Vec<char> = src.chars().collect();
    let (mut out, mut i, mut line) = (Vec::new(), 0, 1);
    let at = |i: usize| c.get(i).copied().unwrap_or('\0');
    // skips a quoted string opening at `i` (escapes honoured unless raw, closed by `"` and `hashes` #)
    let string_end = |mut i: usize, raw: bool, hashes: usize, line: &mut usize| {
        i += 1;
        while i < c.len() {
            match c[i] {
                '\\' if !raw => i += 1,
                '\n' => *line += 1,
                '"' if (1..=hashes).all(|k| at(i + k) == '#') => return i + 1 + hashes,
                _ => {}
            }
            i += 1;
        }
        i
    };
    while i < c.len() {
        let ch = c[i];
        if ch == '\n' {
            line += 1;
            i += 1;
        } else if ch == '/' && at(i + 1) == '/' {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if ch == '/' && at(i + 1) == '*' {
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && at(i + 1) == '*' {
                    depth += 1;
                    i += 2;
                } else if c[i] == '*' && at(i + 1) == '/' {
                    depth -= 1;
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    line += usize::from(c[i] == '\n');
                    i += 1;
                }
            }
        } else if ch == '"' {
            i = string_end(i, false, 0, &mut line);
        } else if ch == '\'' {
            // a char literal, or a lifetime (`'a` with no closing quote)
            if at(i + 1) == '\\' {
                i += 2;
                while i < c.len() && c[i] != '\'' {
                    i += 1;
                }
                i += 1;
            } else if at(i + 2) == '\'' {
                i += 3;
            } else {
                i += 1;
            }
        } else if ch.is_alphabetic() || ch == '_' {
            let start = i;
            while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_') {
                i += 1;
            }
            let word: String = c[start..i].iter().collect();
            let hashes = (0..).take_while(|k| at(i + k) == '#').count();
            if matches!(word.as_str(), "r" | "br" | "cr") && at(i + hashes) == '"' {
                i = string_end(i + hashes, true, hashes, &mut line);
            } else if matches!(word.as_str(), "b" | "c") && at(i) == '"' {
                i = string_end(i, false, 0, &mut line);
            } else if word == "b" && at(i) == '\'' {
                continue; // the char literal after it is skipped next round
            } else {
                out.push(Token { text: word, line });
            }
        } else if ch.is_ascii_digit() {
            while i < c.len() && (c[i].is_alphanumeric() || c[i] == '_' || c[i] == '.' && at(i + 1).is_ascii_digit()) {
                i += 1;
            }
        } else if ch == ':' && at(i + 1) == ':' {
            out.push(Token { text: "::".into(), line });
            i += 2;
        } else if !ch.is_whitespace() {
            out.push(Token { text: ch.to_string(), line });
            i += 1;
        } else {
            i += 1;
        }
    }
    out
}

/// One `use` tree from `t[*i]` on, below `prefix`: each leaf's path and the name it binds (None for a glob).
fn use_tree(t: &[Token], i: &mut usize, prefix: Vec<String>, out: &mut Vec<(Vec<String>, Option<String>)>) {
    let mut path = prefix;
    loop {
        match t.get(*i).map(|x| x.text.as_str()) {
            Some("::") => *i += 1,
            Some("*") => {
                *i += 1;
                out.push((path, None));
                return;
            }
            Some("{") => {
                *i += 1;
                while t.get(*i).is_some_and(|x| x.text != "}") {
                    let before = *i;
                    use_tree(t, i, path.clone(), out);
                    // past the comma, or past a token no tree starts with
                    if *i == before || t.get(*i).is_some_and(|x| x.text == ",") {
                        *i += 1;
                    }
                }
                *i += 1;
                return;
            }
            Some("self") if !path.is_empty() && !matches!(path.last().map(String::as_str), Some("super" | "self")) => {
                *i += 1;
            }
            Some(word) if word.starts_with(|ch: char| ch.is_alphabetic() || ch == '_') && word != "as" => {
                path.push(word.to_string());
                *i += 1;
            }
            _ => break,
        }
    }
    let mut name = path.last().cloned().filter(|n| n != "self" && n != "super" && n != "crate");
    if t.get(*i).is_some_and(|x| x.text == "as") {
        name = t.get(*i + 1).map(|x| x.text.clone()).filter(|n| n != "_");
        *i += 2;
    }
    out.push((path, name));
}

/// A path as a module writes it: from the crate root (`crate::`, `super::`, `self::`, resolved here), or from the
/// module itself (a `use` of one of its submodules, of a name it imported, or of another crate).
#[derive(Debug, Clone, PartialEq)]
enum Named {
    Root(Vec<String>),
    Local(ModPath, Vec<String>),
}

impl Named {
    fn of(here: &ModPath, written: &[String]) -> Option<Named> {
        let mut abs = match written.first().map(String::as_str) {
            Some("crate") => return Some(Named::Root(written[1..].to_vec())),
            Some("super" | "self") => here.clone(),
            _ => return Some(Named::Local(here.clone(), written.to_vec())),
        };
        for (k, s) in written.iter().enumerate() {
            match s.as_str() {
                "super" => {
                    abs.pop()?;
                }
                "self" => {}
                _ => {
                    abs.extend(written[k..].iter().cloned());
                    break;
                }
            }
        }
        Some(Named::Root(abs))
    }

    fn then(&self, tail: &[String]) -> Named {
        match self {
            Named::Root(p) => Named::Root([p, tail].concat()),
            Named::Local(base, p) => Named::Local(base.clone(), [p, tail].concat()),
        }
    }
}

/// What one module says: the paths it names (with their line), the names its `use`s bind, in which file.
#[derive(Default)]
struct Module {
    file: String,
    paths: Vec<(Named, usize)>,
    binds: BTreeMap<String, Named>,
}

/// Every module of src/ (files and the inline ones in them), by path; main.rs (the binary) is not the library's.
fn modules() -> BTreeMap<ModPath, Module> {
    let src = root().join("src");
    let mut files = Vec::new();
    let mut dirs = vec![src.clone()];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).expect("src/ is readable") {
            let p = e.expect("a directory entry").path();
            if p.is_dir() {
                dirs.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                files.push(p);
            }
        }
    }
    let mut out: BTreeMap<ModPath, Module> = BTreeMap::new();
    for file in files {
        let rel = file.strip_prefix(&src).expect("under src/");
        let mut path: ModPath = rel.with_extension("").iter().map(|s| s.to_string_lossy().into_owned()).collect();
        // the binary (main.rs and its subcommands in commands/) is a crate of its own: it reaches the library's
        // rooms only as `hydrolens::…`, from above them all
        if path == ["main"] || path.first().is_some_and(|r| r == "commands") {
            continue;
        }
        if path.last().is_some_and(|l| l == "mod" || l == "lib") {
            path.pop();
        }
        let text = std::fs::read_to_string(&file).expect("a readable source file");
        scan(&tokens(&text), path, &Path::new("src").join(rel).display().to_string(), &mut out);
    }
    out
}

/// Reads one file's tokens into `out`: its module (`path`) and the inline modules in it. A module names the modules
/// it declares (it uses what it holds).
fn scan(t: &[Token], path: ModPath, file: &str, out: &mut BTreeMap<ModPath, Module>) {
    // the modules open, each with the brace depth it closes at
    let mut stack: Vec<(ModPath, usize)> = vec![(path, 0)];
    let mut depth = 0;
    let mut i = 0;
    let word = |i: usize| t.get(i).is_some_and(|x| x.text.starts_with(|ch: char| ch.is_alphabetic() || ch == '_'));
    while i < t.len() {
        let here = stack.last().expect("the file's module").0.clone();
        let m = out.entry(here.clone()).or_insert_with(|| Module { file: file.to_string(), ..Module::default() });
        let after_colons = i > 0 && t[i - 1].text == "::";
        match t[i].text.as_str() {
            "{" => depth += 1,
            "}" => {
                depth -= 1;
                if stack.len() > 1 && stack.last().is_some_and(|s| s.1 == depth) {
                    stack.pop();
                }
            }
            "mod" if word(i + 1) => {
                let child: ModPath = here.iter().cloned().chain([t[i + 1].text.clone()]).collect();
                m.paths.push((Named::Root(child.clone()), t[i].line));
                if t.get(i + 2).is_some_and(|x| x.text == "{") {
                    stack.push((child, depth));
                    depth += 1;
                    i += 3;
                    continue;
                }
            }
            "use" => {
                let line = t[i].line;
                i += 1;
                let mut leaves = Vec::new();
                use_tree(t, &mut i, Vec::new(), &mut leaves);
                for (p, name) in leaves {
                    let Some(named) = Named::of(&here, &p) else { continue };
                    if let Some(n) = name {
                        m.binds.insert(n, named.clone());
                    }
                    m.paths.push((named, line));
                }
                continue;
            }
            "crate" | "super" | "self" if !after_colons && t.get(i + 1).is_some_and(|x| x.text == "::") => {
                let line = t[i].line;
                let mut p = vec![t[i].text.clone()];
                i += 1;
                while t.get(i).is_some_and(|x| x.text == "::") && word(i + 1) {
                    p.push(t[i + 1].text.clone());
                    i += 2;
                }
                if let Some(named) = Named::of(&here, &p) {
                    m.paths.push((named, line));
                }
                continue;
            }
            _ => {}
        }
        i += 1;
    }
}

/// The graph's nodes and edges, with where each edge was first seen.
struct Graph {
    edges: BTreeMap<String, BTreeMap<String, String>>,
}

impl Graph {
    fn of(modules: &BTreeMap<ModPath, Module>) -> Graph {
        let known = |p: &[String]| modules.contains_key(p);
        // the module a path leads to: the longest module it starts with, through the names `use`s bind (an import
        // or a re-export leads on to where the name is defined); None for another crate's
        let resolve = |named: &Named| -> Option<ModPath> {
            let mut cur = named.clone();
            for _ in 0..16 {
                let p = match &cur {
                    Named::Root(p) => p.clone(),
                    Named::Local(base, rest) => {
                        let first = rest.first()?;
                        if known(&[&base[..], &rest[..1]].concat()) {
                            [&base[..], &rest[..]].concat()
                        } else {
                            cur = modules.get(base)?.binds.get(first)?.then(&rest[1..]);
                            continue;
                        }
                    }
                };
                let n = (0..=p.len()).rev().find(|&k| known(&p[..k]))?;
                match modules.get(&p[..n]).and_then(|m| m.binds.get(p.get(n)?)) {
                    Some(bound) => cur = bound.then(&p[n + 1..]),
                    None => return Some(p[..n].to_vec()),
                }
            }
            None
        };
        let mut edges: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
        for (path, m) in modules {
            let from = node(path);
            edges.entry(from.clone()).or_default();
            for (p, line) in &m.paths {
                let Some(to) = resolve(p).map(|t| node(&t)) else { continue };
                if to != from {
                    edges.entry(from.clone()).or_default().entry(to).or_insert_with(|| format!("{}:{line}", m.file));
                }
            }
        }
        Graph { edges }
    }

    /// The circles: groups of nodes that each reach all the others.
    fn circles(&self) -> Vec<Vec<String>> {
        let reach = |from: &str| {
            let (mut seen, mut todo) = (BTreeSet::new(), vec![from]);
            while let Some(v) = todo.pop() {
                for to in self.edges.get(v).into_iter().flat_map(|e| e.keys()) {
                    if seen.insert(to.as_str()) {
                        todo.push(to);
                    }
                }
            }
            seen
        };
        let reaches: BTreeMap<&str, BTreeSet<&str>> = self.edges.keys().map(|v| (v.as_str(), reach(v))).collect();
        let mut out: Vec<Vec<String>> = Vec::new();
        for (v, r) in &reaches {
            if r.contains(v) && !out.iter().flatten().any(|n| n == v) {
                out.push(
                    r.iter()
                        .filter(|u| reaches.get(*u).is_some_and(|back| back.contains(v)))
                        .map(|u| u.to_string())
                        .collect(),
                );
            }
        }
        out
    }

    /// The graph with each node renamed by `name` (None: left out), the edges between nodes of one name dropped.
    fn view(&self, name: impl Fn(&str) -> Option<String>) -> Graph {
        let mut edges: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
        for (from, e) in &self.edges {
            let Some(from) = name(from) else { continue };
            let out = edges.entry(from.clone()).or_default();
            for (to, at) in e {
                if let Some(to) = name(to).filter(|t| *t != from) {
                    out.entry(to).or_insert_with(|| at.clone());
                }
            }
        }
        Graph { edges }
    }

    /// Each edge inside a group, with where it was seen.
    fn explain(&self, group: &[String]) -> String {
        let mut s = String::new();
        for from in group {
            for (to, at) in self.edges.get(from).into_iter().flatten() {
                if group.contains(to) {
                    s.push_str(&format!("\n  {from} → {to} ({at})"));
                }
            }
        }
        s
    }
}

/// A module's node: its room, or for a split room its module (`service::state`); the root is `crate`.
fn node(path: &[String]) -> String {
    match path {
        [] => "crate".into(),
        [room, module, ..] if SPLIT.contains(&room.as_str()) => format!("{room}::{module}"),
        [room, ..] => room.clone(),
    }
}

/// The floors of a `# Layout` section (`//! - [`a`], [`b`]: …`): the rooms each bullet names before its colon.
fn floors(file: &str) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(root().join(file)).expect("readable");
    let section = text.lines().skip_while(|l| !l.starts_with("//! # Layout")).skip(1);
    let mut out = Vec::new();
    for l in section.take_while(|l| l.starts_with("//!")) {
        if let Some(bullet) = l.strip_prefix("//! - ") {
            let head = bullet.split_once(": ").map_or(bullet, |(h, _)| h);
            out.push(head.split("[`").skip(1).filter_map(|s| s.split_once("`]")).map(|(r, _)| r.to_string()).collect());
        }
    }
    out
}

/// Checks a graph against the `# Layout` of `file`: every node has a floor, and uses only nodes on lower floors.
fn check_floors(g: &Graph, file: &str, errors: &mut Vec<String>) {
    let layout = floors(file);
    let floor = |n: &str| layout.iter().position(|f| f.iter().any(|r| r == n));
    for (from, e) in &g.edges {
        let Some(a) = floor(from) else {
            errors.push(format!("{from} is not in {file}'s # Layout"));
            continue;
        };
        for (to, at) in e {
            if floor(to).is_some_and(|b| b >= a) {
                errors.push(format!("{from} uses {to} ({at}), which {file}'s # Layout lists with it or after it"));
            }
        }
    }
}

#[test]
fn no_room_reaches_up_and_no_circle_among_rooms_or_service_modules() {
    let g = Graph::of(&modules());
    let mut errors: Vec<String> = g
        .circles()
        .iter()
        .map(|group| format!("an import circle among {}:{}", group.join(", "), g.explain(group)))
        .collect();
    let rooms = g.view(|n| Some(n.split("::").next().unwrap_or(n).to_string()).filter(|r| r != "crate"));
    check_floors(&rooms, "src/lib.rs", &mut errors);
    let service = g.view(|n| n.strip_prefix("service::").map(String::from));
    check_floors(&service, "src/service/mod.rs", &mut errors);
    assert!(errors.is_empty(), "{}", errors.join("\n"));
}
#[test]
fn the_reader_sees_the_paths_a_module_names_and_finds_circles() {
    let src = "//! crate::a in a comment\nuse super::{b::{self, X}, c as d};\nuse crate::e::*;\nuse std::sync::Arc;\n\
               fn f<'a>(x: &'a str) { let s = \"crate::g\"; let c = '\"'; crate::h::i(); super::super::j::k(); }\n\
               #[cfg(test)]\nmod tests {\n    use super::*;\n    fn t() { super::super::l::m(); }\n}\n";
    let mut out = BTreeMap::new();
    scan(&tokens(src), vec!["service".into(), "x".into()], "x.rs", &mut out);
    let shown = |n: &Named| match n {
        Named::Root(p) => p.join("::"),
        Named::Local(_, p) => format!("~{}", p.join("::")),
    };
    let paths = |m: &[&str]| -> Vec<String> {
        let m: ModPath = m.iter().map(|s| s.to_string()).collect();
        out[&m].paths.iter().map(|(p, _)| shown(p)).collect()
    };
    let x = ["service", "x"];
    assert_eq!(
        paths(&x),
        ["service::b", "service::b::X", "service::c", "e", "~std::sync::Arc", "h::i", "j::k", "service::x::tests"]
    );
    assert_eq!(paths(&["service", "x", "tests"]), ["service::x", "service::l::m"]);
    assert_eq!(shown(&out[&x.map(String::from).to_vec()].binds["d"]), "service::c");
    let mut edges: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    for (from, to) in [("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")] {
        edges.entry(from.into()).or_default().insert(to.into(), String::new());
    }
    assert_eq!(Graph { edges }.circles(), [["a", "b", "c"]]);
}
