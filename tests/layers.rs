//! The library's layers import only downward (README, *Layout*): every `crate::X` path in
//! `src/**/*.rs` names a module of the same layer or a lower one. Comments are skipped; unit tests
//! inside a module are held to the same rule. `src/main.rs` (the CLI, on top) may use anything.

use std::fs;
use std::path::Path;

/// Bottom to top; modules in one entry are peers and may import each other.
const LAYERS: &[&[&str]] = &[
    &["math", "color", "rng", "atomic_write", "image", "allocator"],
    &["scene"],
    &["geometry", "material"],
    &["light"],
    &["optim"],
    &["render"],
    &["scene_data"],
    &["eval", "prior"],
    &["fit"],
    &["report"],
    &["jobs"],
];

fn layer_of(module: &str) -> Option<usize> {
    LAYERS.iter().position(|layer| layer.contains(&module))
}

/// The top-level module names a line of code refers to as `crate::NAME` (or `crate::{A, B::…}`).
fn crate_paths(code: &str) -> Vec<String> {
    let ident = |s: &str| s.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect::<String>();
    let mut out = Vec::new();
    for (i, _) in code.match_indices("crate::") {
        let rest = &code[i + "crate::".len()..];
        if let Some(list) = rest.strip_prefix('{') {
            // Top-level entries of the braced list: the identifier after `{` or after a comma at depth 0.
            let mut depth = 0;
            let mut start = true;
            for (j, c) in list.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => start = true,
                    c if start && !c.is_whitespace() => {
                        out.push(ident(&list[j..]));
                        start = false;
                    }
                    _ => {}
                }
            }
        } else {
            out.push(ident(rest));
        }
    }
    out
}

fn rust_files(dir: &Path, out: &mut Vec<std::path::PathBuf>) {
    for entry in fs::read_dir(dir).expect("src/ is readable") {
        let path = entry.expect("directory entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn every_src_module_imports_only_its_own_layer_or_below() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    files.sort();
    let mut upward = Vec::new();
    let mut unknown = Vec::new();
    for file in &files {
        let rel = file.strip_prefix(&src).expect("under src/");
        let first = rel.components().next().expect("a path").as_os_str().to_string_lossy().into_owned();
        let module = first.trim_end_matches(".rs").to_string();
        if module == "main" || module == "lib" {
            continue;
        }
        let Some(own) = layer_of(&module) else {
            unknown.push(format!("src/{} (module {module:?})", rel.display()));
            continue;
        };
        let text = fs::read_to_string(file).expect("source file is UTF-8");
        for (n, line) in text.lines().enumerate() {
            let code = line.split("//").next().unwrap_or("");
            for target in crate_paths(code) {
                match layer_of(&target) {
                    Some(t) if t <= own => {}
                    Some(_) => upward.push(format!("src/{}:{}: {module} imports {target}: {}", rel.display(), n + 1, line.trim())),
                    None => unknown.push(format!("src/{}:{}: crate::{target} (module not in LAYERS)", rel.display(), n + 1)),
                }
            }
        }
    }
    assert!(unknown.is_empty(), "modules missing from LAYERS (add them to tests/layers.rs and the README):\n{}", unknown.join("\n"));
    assert!(upward.is_empty(), "imports that go up a layer (README, *Layout*):\n{}", upward.join("\n"));
}

#[test]
fn the_scanner_sees_plain_and_braced_paths() {
    assert_eq!(crate_paths("use crate::scene::Camera;"), ["scene"]);
    assert_eq!(crate_paths("use crate::{fit::x, render::{a, b}, jobs};"), ["fit", "render", "jobs"]);
    assert_eq!(crate_paths("let p = crate::image::io::read_png(&a); crate::color::f(1)"), ["image", "color"]);
    assert!(crate_paths("use super::tape;").is_empty());
}
