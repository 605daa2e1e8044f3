//! The broker's modules stay in layers: no module imports, through others, a module that
//! imports it (issue 31). A change to the wire or the domain then stays below the session
//! layer, and the session layer below the planes and the assembly (`docs/architecture.md`
//! draws the floors).
//!
//! The graph is read from the source, not from the compiler: every file of `broker/src`
//! is a module (`foo.rs`, `foo/mod.rs`), and it depends on each module that a `crate::`,
//! `super::` or `self::` path in it names (the longest prefix of the path that is a
//! module), and on each of its own submodules it names (`close::End` in `session/mod.rs`).
//! What only tests use does not count: `#[cfg(test)]` items and `tests.rs` files are left
//! out. A submodule naming the module that contains it (`super::Session`) is the inside of
//! one room, not an import between rooms, and does not count either; anything else that
//! closes a loop does, and the test names the loop.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A module path: `["session", "close"]` for `session/close.rs`.
type Module = Vec<String>;

/// Who depends on whom, with the names that tie them (for the message).
type Graph = BTreeMap<Module, BTreeMap<Module, BTreeSet<String>>>;

#[test]
fn broker_modules_import_each_other_in_no_cycle() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let files = read_tree(&src);
    assert!(
        files.len() > 20,
        "read only {} files of {}",
        files.len(),
        src.display()
    );
    let graph = graph(&files);
    if let Some(cycle) = find_cycle(&graph) {
        panic!("{}", describe(&graph, &cycle));
    }
}

/// The check itself finds a loop: three modules in a circle, one of them through a
/// submodule, are named in order.
#[test]
fn a_cycle_is_found_and_named() {
    let files = BTreeMap::from([
        (module("a"), "use crate::b::Thing;\n".to_owned()),
        (
            module("b"),
            "mod inner;\npub fn f() { inner::g() }\n".to_owned(),
        ),
        (
            module("b::inner"),
            "use crate::c::{self, Other};\n".to_owned(),
        ),
        (
            module("c"),
            "pub fn h() -> crate::a::A { todo!() }\n#[cfg(test)]\nmod tests { use crate::d; }\n"
                .to_owned(),
        ),
        (module("d"), "use crate::c;\n".to_owned()),
    ]);
    let looped = graph(&files);
    let cycle = find_cycle(&looped).expect("a -> b -> b::inner -> c -> a is a cycle");
    let text = describe(&looped, &cycle);
    for part in [
        "a -> b",
        "b -> b::inner",
        "b::inner -> c",
        "c -> a",
        "Thing",
    ] {
        assert!(text.contains(part), "{part} missing from: {text}");
    }
    // The test-only import of `d` is not an edge; `d -> c` alone closes no loop.
    assert!(
        !looped[&module("c")].contains_key(&module("d")),
        "{looped:?}"
    );
    // A submodule using what its module holds is no cycle.
    let files = BTreeMap::from([
        (module("s"), "mod close;\nuse close::End;\n".to_owned()),
        (module("s::close"), "use super::Session;\n".to_owned()),
    ]);
    assert_eq!(find_cycle(&graph(&files)), None);
}

fn module(path: &str) -> Module {
    path.split("::").map(str::to_owned).collect()
}

/// Every `.rs` file under `src`, by module path, with the code of its non-test items.
fn read_tree(src: &Path) -> BTreeMap<Module, String> {
    let mut files = BTreeMap::new();
    let mut dirs: Vec<PathBuf> = vec![src.to_owned()];
    while let Some(dir) = dirs.pop() {
        for entry in std::fs::read_dir(&dir).expect("broker/src is readable") {
            let path = entry.expect("a directory entry").path();
            if path.is_dir() {
                dirs.push(path);
                continue;
            }
            if path.extension().is_none_or(|e| e != "rs") {
                continue;
            }
            let relative = path.strip_prefix(src).expect("under src");
            let mut parts: Module = relative
                .with_extension("")
                .iter()
                .map(|p| p.to_string_lossy().into_owned())
                .collect();
            match parts.last().map(String::as_str) {
                // The crate roots: `crate::` from them is every module's business.
                Some("lib" | "main") if parts.len() == 1 => continue,
                Some("tests") => continue,
                Some("mod") => {
                    parts.pop();
                }
                _ => {}
            }
            let text = std::fs::read_to_string(&path).expect("a source file is UTF-8");
            files.insert(parts, text);
        }
    }
    files
}

/// The modules each module depends on, from the paths its non-test code names.
fn graph(files: &BTreeMap<Module, String>) -> Graph {
    let mut graph = Graph::new();
    for (me, text) in files {
        let code = without_tests(&strip(text));
        let children = declared_children(&code);
        let mut edges: BTreeMap<Module, BTreeSet<String>> = BTreeMap::new();
        for path in paths(&code, me, &children) {
            let Some(target) = (1..=path.len())
                .rev()
                .map(|n| path[..n].to_vec())
                .find(|m| files.contains_key(m))
            else {
                continue;
            };
            // Itself, or a module that contains it: the inside of one room.
            if target.len() <= me.len() && me[..target.len()] == target[..] {
                continue;
            }
            let name = path.last().cloned().unwrap_or_default();
            edges.entry(target).or_default().insert(name);
        }
        graph.insert(me.clone(), edges);
    }
    graph
}

/// The source with comments, string and character literals blanked (braces and paths in
/// them are not code).
fn strip(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match b[i] {
            b'/' if b.get(i + 1) == Some(&b'/') => {
                while i < b.len() && b[i] != b'\n' {
                    i += 1;
                }
            }
            b'/' if b.get(i + 1) == Some(&b'*') => {
                let mut depth = 0;
                while i < b.len() {
                    if b[i] == b'/' && b.get(i + 1) == Some(&b'*') {
                        depth += 1;
                        i += 2;
                    } else if b[i] == b'*' && b.get(i + 1) == Some(&b'/') {
                        depth -= 1;
                        i += 2;
                        if depth == 0 {
                            break;
                        }
                    } else {
                        i += 1;
                    }
                }
                out.push(b' ');
            }
            b'r' if matches!(b.get(i + 1), Some(b'#' | b'"'))
                && (i == 0 || !is_ident(b[i - 1])) =>
            {
                let hashes = b[i + 1..].iter().take_while(|&&c| c == b'#').count();
                let open = i + 1 + hashes;
                if b.get(open) != Some(&b'"') {
                    out.push(b[i]);
                    i += 1;
                    continue;
                }
                let close: Vec<u8> = std::iter::once(b'"')
                    .chain(std::iter::repeat_n(b'#', hashes))
                    .collect();
                i = open + 1;
                while i < b.len() && !b[i..].starts_with(&close) {
                    i += 1;
                }
                i += close.len();
                out.extend_from_slice(b"\"\"");
            }
            b'"' => {
                i += 1;
                while i < b.len() && b[i] != b'"' {
                    i += if b[i] == b'\\' { 2 } else { 1 };
                }
                i += 1;
                out.extend_from_slice(b"\"\"");
            }
            // A character literal ('{', '\'', '\u{7f}'), not a lifetime ('a).
            b'\'' => {
                let end = if b.get(i + 1) == Some(&b'\\') {
                    b[i + 2..]
                        .iter()
                        .position(|&c| c == b'\'')
                        .map(|p| i + 2 + p)
                } else if b.get(i + 2) == Some(&b'\'') {
                    Some(i + 2)
                } else {
                    // A multi-byte character, or a lifetime.
                    let rest = &text[i + 1..];
                    let c = rest.chars().next().map_or(1, char::len_utf8);
                    (rest.as_bytes().get(c) == Some(&b'\'')).then_some(i + 1 + c)
                };
                match end {
                    Some(end) => {
                        out.extend_from_slice(b"' '");
                        i = end + 1;
                    }
                    None => {
                        out.push(b'\'');
                        i += 1;
                    }
                }
            }
            c => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// The code without its `#[cfg(test)]` items (a test module, a test-only function).
fn without_tests(code: &str) -> String {
    let mut out = String::with_capacity(code.len());
    let mut rest = code;
    while let Some(at) = rest.find("#[cfg(test)]") {
        out.push_str(&rest[..at]);
        let item = &rest[at..];
        // The item ends at its first `;` outside braces, or at the brace closing its body.
        let mut depth = 0usize;
        let mut end = item.len();
        for (i, c) in item.char_indices() {
            match c {
                '{' => depth += 1,
                '}' => {
                    depth = depth.saturating_sub(1);
                    if depth == 0 {
                        end = i + 1;
                        break;
                    }
                }
                ';' if depth == 0 => {
                    end = i + 1;
                    break;
                }
                _ => {}
            }
        }
        rest = &item[end..];
    }
    out.push_str(rest);
    out
}

/// The submodules a file declares (`mod close;`, `pub mod table;`).
fn declared_children(code: &str) -> BTreeSet<String> {
    let mut children = BTreeSet::new();
    let tokens: Vec<&str> = code
        .split(|c: char| !(c.is_alphanumeric() || c == '_' || c == ';'))
        .filter(|t| !t.is_empty())
        .collect();
    for pair in tokens.windows(2) {
        if pair[0] == "mod" {
            if let Some(name) = pair[1].strip_suffix(';') {
                children.insert(name.to_owned());
            }
        }
    }
    children
}

/// Every module path the code names, made absolute (`crate::`-relative).
fn paths(code: &str, me: &Module, children: &BTreeSet<String>) -> Vec<Module> {
    let b = code.as_bytes();
    let mut found = Vec::new();
    let mut i = 0;
    while i < b.len() {
        if !is_ident(b[i]) || (i > 0 && (is_ident(b[i - 1]) || b[i - 1] == b'$')) {
            i += 1;
            continue;
        }
        let start = i;
        while i < b.len() && is_ident(b[i]) {
            i += 1;
        }
        let word = &code[start..i];
        // Part of a longer path (`a::word`): its head was seen already.
        let after_colons = start >= 2 && &code[start - 2..start] == "::";
        if after_colons || !code[i..].starts_with("::") {
            continue;
        }
        let base: Module = match word {
            "crate" => Vec::new(),
            "self" => me.clone(),
            "super" => {
                let mut base = me.clone();
                base.pop();
                let mut j = i;
                while code[j..].starts_with("::super") {
                    base.pop();
                    j += "::super".len();
                }
                i = j;
                base
            }
            child if children.contains(child) => {
                let mut base = me.clone();
                base.push(child.to_owned());
                base
            }
            _ => continue,
        };
        // `i` is at the `::` after the head.
        let (trees, end) = use_tree(code, i);
        for tree in trees {
            let mut path = base.clone();
            path.extend(tree);
            found.push(path);
        }
        i = end.max(i + 1);
    }
    found
}

/// The paths of a use tree that starts at `code[at..]` with `::`: `::a::b`, `::{a, b::c}`.
/// Returns them (each a list of segments) and where the tree ends.
fn use_tree(code: &str, at: usize) -> (Vec<Module>, usize) {
    let b = code.as_bytes();
    let mut i = at;
    let mut prefix: Module = Vec::new();
    loop {
        if !code[i..].starts_with("::") {
            return (vec![prefix], i);
        }
        i += 2;
        while i < b.len() && b[i].is_ascii_whitespace() {
            i += 1;
        }
        if b.get(i) == Some(&b'{') {
            let mut out = Vec::new();
            i += 1;
            loop {
                while i < b.len() && (b[i].is_ascii_whitespace() || b[i] == b',') {
                    i += 1;
                }
                if i >= b.len() || b[i] == b'}' {
                    return (out, i + 1);
                }
                let start = i;
                while i < b.len() && is_ident(b[i]) {
                    i += 1;
                }
                if start == i {
                    // `*`, or something this reader does not know: skip a byte.
                    i += 1;
                    continue;
                }
                let head = code[start..i].to_owned();
                let (tails, end) = use_tree(code, i);
                for tail in tails {
                    let mut path = prefix.clone();
                    if head != "self" {
                        path.push(head.clone());
                    }
                    path.extend(tail);
                    out.push(path);
                }
                i = end;
                // `as alias`
                let rest = code[i..].trim_start();
                if let Some(alias) = rest.strip_prefix("as ") {
                    let skip = alias.trim_start();
                    let len = skip.bytes().take_while(|&c| is_ident(c)).count();
                    i = code.len() - skip.len() + len;
                }
            }
        }
        let start = i;
        while i < b.len() && is_ident(b[i]) {
            i += 1;
        }
        if start == i {
            return (vec![prefix], i);
        }
        prefix.push(code[start..i].to_owned());
    }
}

fn is_ident(c: u8) -> bool {
    c.is_ascii_alphanumeric() || c == b'_'
}

/// A cycle of the graph, if there is one: its modules in order, the first repeated last.
fn find_cycle(graph: &Graph) -> Option<Vec<Module>> {
    #[derive(Clone, Copy, PartialEq)]
    enum Mark {
        New,
        Open,
        Done,
    }
    let mut marks: BTreeMap<&Module, Mark> = graph.keys().map(|m| (m, Mark::New)).collect();
    for root in graph.keys() {
        if marks[root] != Mark::New {
            continue;
        }
        // Depth first, with the path of open modules on a stack of iterators.
        let mut stack: Vec<(&Module, Vec<&Module>)> =
            vec![(root, graph[root].keys().collect::<Vec<_>>())];
        marks.insert(root, Mark::Open);
        while let Some((node, next)) = stack.last_mut() {
            let node: &Module = node;
            match next.pop() {
                Some(to) => match marks.get(to).copied() {
                    Some(Mark::New) => {
                        marks.insert(to, Mark::Open);
                        stack.push((to, graph[to].keys().collect()));
                    }
                    Some(Mark::Open) => {
                        let from = stack.iter().position(|(m, _)| *m == to).expect("open");
                        let mut cycle: Vec<Module> =
                            stack[from..].iter().map(|(m, _)| (*m).clone()).collect();
                        cycle.push(to.clone());
                        return Some(cycle);
                    }
                    _ => {}
                },
                None => {
                    marks.insert(node, Mark::Done);
                    stack.pop();
                }
            }
        }
    }
    None
}

fn describe(graph: &Graph, cycle: &[Module]) -> String {
    let name = |m: &Module| m.join("::");
    let mut text = format!(
        "broker/src imports in a cycle: {}\n",
        cycle.iter().map(name).collect::<Vec<_>>().join(" -> ")
    );
    for pair in cycle.windows(2) {
        let names: Vec<&str> = graph[&pair[0]][&pair[1]]
            .iter()
            .map(String::as_str)
            .collect();
        text.push_str(&format!(
            "  {} -> {}: {}\n",
            name(&pair[0]),
            name(&pair[1]),
            names.join(", ")
        ));
    }
    text.push_str(
        "a module below must not import one above it: move the shared type down, or pass \
         it in (docs/architecture.md, \"Layers\")",
    );
    text
}
