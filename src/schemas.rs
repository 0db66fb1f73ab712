//! The JSON schemas of our artifacts, generated from the Rust types that write them.
//!
//! `schemas/tables/<table>.json` documents each Parquet table (from [`crate::io::tables`]),
//! `schemas/mcap/<schema>.json` each MCAP channel's message schema (from
//! [`crate::io::mcap_writer`]), `schemas/diagnosis.schema.json` the diagnosis document. `hbmu schemas --out schemas` regenerates them; a test fails when
//! the checked-in files differ from what the code writes.

use std::collections::BTreeMap;
use std::path::Path;

/// Every generated schema file: relative path → pretty JSON text (with trailing newline).
pub fn generate() -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    let pretty = |v: &serde_json::Value| {
        let mut s = serde_json::to_string_pretty(v).expect("schema serialises");
        s.push('\n');
        s
    };
    let stage_tables = [
        &crate::io::tables::extract::MODES,
        &crate::io::tables::extract::POINT_FLAGS,
        &crate::io::tables::pairs::PAIRS,
        &crate::io::tables::pairs::PRESENCE,
        &crate::io::tables::update::POPULATION,
        &crate::io::tables::update::BOARDS,
        &crate::io::tables::update::BOARDS_PHYSICAL,
        &crate::io::tables::update::SUMMARY,
        &crate::io::tables::update::STAGES,
        &crate::io::tables::update::RESIDUALS,
        &crate::io::tables::update::JOINTS,
        &crate::io::tables::update::POPULATION_JOINTS,
        &crate::io::tables::propagate::PREDICTIONS,
        &crate::io::tables::report::TABLE2,
        &crate::io::tables::report::INTERVALS,
        &crate::io::tables::diagnose::DIAGNOSIS,
        &crate::io::tables::diagnose::MODES,
    ];
    for t in crate::io::tables::all_tables()
        .into_iter()
        .chain(stage_tables)
        .chain(crate::io::tables::diagnose::SPECS)
    {
        out.insert(format!("tables/{}.json", t.name), pretty(&t.json_schema()));
    }
    out.insert(
        "diagnosis.schema.json".into(),
        pretty(
            &serde_json::to_value(schemars::schema_for!(crate::stage::diagnose::DiagnosisDoc))
                .expect("schema serialises"),
        ),
    );
    for ch in crate::io::mcap_writer::channel_schemas() {
        let (name, mut v) = (ch.schema_name, ch.schema);
        if let Some(o) = v.as_object_mut() {
            o.insert(
                "x-mcap-schema-name".into(),
                serde_json::Value::String(name.into()),
            );
        }
        let file = format!("mcap/{}.json", name.trim_start_matches("hbmu."));
        out.entry(file).or_insert_with(|| pretty(&v));
    }
    out
}

/// Write every schema under `dir`, atomically per file.
pub fn write_all(dir: &Path) -> std::io::Result<()> {
    for (rel, text) in generate() {
        crate::io::atomic::write_bytes(&dir.join(rel), text.as_bytes())?;
    }
    Ok(())
}
