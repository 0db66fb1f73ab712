//! The layering of ARCHITECTURE.md as a test: kernels (pure functions over plain data) import
//! no `io`, no `stage` and no clap; `io` imports no `stage`; a stage imports no other stage
//! (the one exception named below); no process-global mutable state outside tests.

use crate::common::repo;
use std::path::{Path, PathBuf};

/// The kernel modules under `src/` (directories or files).
const KERNELS: &[&str] = &[
    "bayes",
    "campaign.rs",
    "diagnose",
    "fem",
    "findings.rs",
    "formats",
    "lab",
    "modal",
    "optim",
    "report",
    "simd.rs",
    "table_spec.rs",
    "uq",
    "update",
];

/// A stage that may import another stage, and why: the diagnosis's refits are updating steps
/// with their own manifests (`refits/<id>/`), run through the update stage's entry points.
const STAGE_TO_STAGE: &[(&str, &str)] = &[("stage/diagnose/refit.rs", "crate::stage::update")];

/// The code of a source file without comments, string literals and `#[cfg(test)]` modules.
fn code_of(text: &str) -> String {
    let b = text.as_bytes();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    while i < b.len() {
        if text[i..].starts_with("//") {
            i = text[i..].find('\n').map_or(b.len(), |k| i + k);
        } else if text[i..].starts_with("/*") {
            i = text[i..].find("*/").map_or(b.len(), |k| i + k + 2);
        } else if b[i] == b'"' && (i == 0 || b[i - 1] != b'\'') {
            let mut j = i + 1;
            while j < b.len() && b[j] != b'"' {
                j += if b[j] == b'\\' { 2 } else { 1 };
            }
            out.push_str("\"\"");
            i = j + 1;
        } else if text[i..].starts_with("#[cfg(test)]") {
            // The item after the attribute: a module block is skipped to its closing brace.
            let rest = &text[i..];
            let item_end = rest.find(['{', ';']).unwrap_or(rest.len());
            if rest[..item_end].contains("mod ") && rest[item_end..].starts_with('{') {
                let mut depth = 0usize;
                let mut j = i + item_end;
                while j < b.len() {
                    match b[j] {
                        b'{' => depth += 1,
                        b'}' => {
                            depth -= 1;
                            if depth == 0 {
                                break;
                            }
                        }
                        _ => {}
                    }
                    j += 1;
                }
                i = j + 1;
            } else {
                i += "#[cfg(test)]".len();
            }
        } else {
            let c = text[i..].chars().next().expect("in bounds");
            out.push(c);
            i += c.len_utf8();
        }
    }
    out
}

/// The forbidden paths a file's code names, given the paths its layer may not import.
fn violations_in(text: &str, forbidden: &[&str]) -> Vec<String> {
    let code = code_of(text);
    forbidden
        .iter()
        .filter(|f| code.contains(**f))
        .map(|f| f.to_string())
        .collect()
}

/// Every `.rs` file under `dir` that is not a test module: files named `tests.rs` or
/// `*_tests.rs`, files under a `tests/` directory, and files declared `#[cfg(test)] mod x;`.
fn sources(dir: &Path) -> Vec<PathBuf> {
    let mut out = vec![];
    let mut stack = vec![dir.to_path_buf()];
    let mut test_mods = vec![];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                if p.file_name().is_some_and(|n| n != "tests") {
                    stack.push(p);
                }
            } else if p.extension().is_some_and(|x| x == "rs") {
                let t = std::fs::read_to_string(&p).unwrap();
                for (k, _) in t.match_indices("#[cfg(test)]") {
                    let rest = t[k + 12..].trim_start();
                    let rest = rest.strip_prefix("pub ").unwrap_or(rest);
                    if let Some(m) = rest.strip_prefix("mod ") {
                        let name: String = m
                            .chars()
                            .take_while(|c| c.is_alphanumeric() || *c == '_')
                            .collect();
                        if m[name.len()..].trim_start().starts_with(';') {
                            let base = p.parent().unwrap();
                            test_mods.push(base.join(format!("{name}.rs")));
                            test_mods.push(base.join(&name).join("mod.rs"));
                        }
                    }
                }
                out.push(p);
            }
        }
    }
    out.retain(|p| {
        let n = p.file_name().unwrap().to_string_lossy();
        !(n == "tests.rs" || n.ends_with("_tests.rs") || test_mods.contains(p))
    });
    out.sort();
    out
}

fn rel(p: &Path) -> String {
    p.strip_prefix(repo().join("src"))
        .unwrap()
        .to_string_lossy()
        .replace('\\', "/")
}

#[test]
fn kernels_import_no_io_stage_or_clap_and_io_no_stage() {
    let src = repo().join("src");
    let mut bad = vec![];
    for k in KERNELS {
        let p = src.join(k);
        assert!(p.exists(), "kernel {k} listed but missing");
        let files = if p.is_dir() { sources(&p) } else { vec![p] };
        for f in files {
            let text = std::fs::read_to_string(&f).unwrap();
            for v in violations_in(
                &text,
                &[
                    "crate::io",
                    "crate::stage",
                    "hbmu::io",
                    "hbmu::stage",
                    "clap",
                ],
            ) {
                bad.push(format!("{} uses {v}", rel(&f)));
            }
        }
    }
    for f in sources(&src.join("io")) {
        let text = std::fs::read_to_string(&f).unwrap();
        for v in violations_in(&text, &["crate::stage", "clap"]) {
            bad.push(format!("{} uses {v}", rel(&f)));
        }
    }
    assert!(
        bad.is_empty(),
        "layering broken (see ARCHITECTURE.md):\n  {}",
        bad.join("\n  ")
    );
}

#[test]
fn a_stage_imports_no_other_stage() {
    let dir = repo().join("src/stage");
    let mut bad = vec![];
    for f in sources(&dir) {
        let r = rel(&f);
        // The stage a file belongs to: `stage/<name>.rs` or `stage/<name>/…`.
        let own = r
            .trim_start_matches("stage/")
            .split(['/', '.'])
            .next()
            .unwrap()
            .to_string();
        if own == "mod" {
            continue;
        }
        let code = code_of(&std::fs::read_to_string(&f).unwrap());
        for (k, _) in code.match_indices("crate::stage::") {
            let rest = &code[k + 14..];
            // `crate::stage::name…` or `crate::stage::{a, b::c, …}`.
            let names: Vec<String> = match rest.strip_prefix('{') {
                Some(list) => list[..list.find('}').unwrap_or(list.len())]
                    .split(',')
                    .map(|n| n.trim().to_string())
                    .collect(),
                None => vec![rest.to_string()],
            };
            for n in names {
                let name: String = n
                    .chars()
                    .take_while(|c| c.is_alphanumeric() || *c == '_')
                    .collect();
                if name.is_empty() {
                    continue;
                }
                let path = format!("crate::stage::{name}");
                let executor = [
                    "run",
                    "exit",
                    "StageOutcome",
                    "StageResult",
                    "progress_bar",
                    "PhaseClock",
                ]
                .contains(&name.as_str());
                let allowed = STAGE_TO_STAGE
                    .iter()
                    .any(|(file, p)| *file == r && *p == path);
                if name != own && !executor && !allowed {
                    bad.push(format!("{r} uses {path}"));
                }
            }
        }
    }
    bad.sort();
    bad.dedup();
    assert!(
        bad.is_empty(),
        "a stage imports another:\n  {}",
        bad.join("\n  ")
    );
}

#[test]
fn no_process_global_mutable_state_outside_tests() {
    let mut bad = vec![];
    for f in sources(&repo().join("src")) {
        let code = code_of(&std::fs::read_to_string(&f).unwrap());
        for line in code.lines() {
            let l = line.trim_start();
            let global = l.starts_with("static ")
                || l.starts_with("pub static ")
                || l.starts_with("pub(crate) static ");
            let mutable = [
                "Mutex", "RwLock", "Cell", "OnceLock", "OnceCell", "Atomic", "LazyLock",
            ]
            .iter()
            .any(|t| l.contains(t));
            if l.contains("thread_local!") || l.contains("static mut ") || (global && mutable) {
                bad.push(format!("{}: {}", rel(&f), l.trim()));
            }
        }
    }
    assert!(
        bad.is_empty(),
        "process-global mutable state:\n  {}",
        bad.join("\n  ")
    );
}

/// The checks can fail: a kernel's import of io or clap is seen, one in a comment, a string
/// or a test module is not.
#[test]
fn the_layer_check_sees_an_import_and_only_an_import() {
    let forbidden = ["crate::io", "crate::stage", "clap"];
    assert_eq!(
        violations_in("use crate::io::tables;\nfn f() {}", &forbidden),
        ["crate::io"]
    );
    assert_eq!(
        violations_in("#[derive(clap::ValueEnum)]\nenum E { A }", &forbidden),
        ["clap"]
    );
    assert!(violations_in("// see crate::io::tables\n/// clap\nfn f() {}", &forbidden).is_empty());
    assert!(violations_in("fn f() { let s = \"crate::stage\"; }", &forbidden).is_empty());
    assert!(violations_in(
        "fn f() {}\n#[cfg(test)]\nmod tests {\n    use crate::io::tables;\n    fn g() { if true { } }\n}\n",
        &forbidden
    )
    .is_empty());
    assert_eq!(
        violations_in(
            "#[cfg(test)]\nmod tests {\n}\nuse crate::stage::x;",
            &forbidden
        ),
        ["crate::stage"]
    );
}
