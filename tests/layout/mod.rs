//! Repository invariants: schema files in sync with the code, module header comments.

mod layers;

use crate::common::repo;

#[test]
fn checked_in_schemas_match_the_code() {
    let generated = hbmu::schemas::generate();
    let mut stale = vec![];
    for (rel, text) in &generated {
        let p = repo().join("schemas").join(rel);
        match std::fs::read_to_string(&p) {
            Ok(t) if &t == text => {}
            _ => stale.push(rel.clone()),
        }
    }
    assert!(
        stale.is_empty(),
        "schemas/ out of date for {stale:?}: run `cargo run -- schemas --out schemas`"
    );
}

#[test]
fn every_source_file_opens_with_a_module_comment() {
    let mut missing = vec![];
    let mut stack = vec![repo().join("src")];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let t = std::fs::read_to_string(&p).unwrap();
                if !t.trim_start().starts_with("//!") {
                    missing.push(p.display().to_string());
                }
            }
        }
    }
    assert!(
        missing.is_empty(),
        "files without a //! header: {missing:?}"
    );
}
