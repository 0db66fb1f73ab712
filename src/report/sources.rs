//! What the validation report takes from the other stages' JSON documents, pure: held-out
//! boards, findings, ingest's counts, why there is no step 2, and the names of copied plots.

use crate::report::html::FindingRow;
use std::collections::BTreeMap;

/// Boards step 1 held out of the updating (update_report.json's `held_out_boards`; absent
/// in reports written before the option).
pub fn held_out_boards(update_report: &serde_json::Value) -> Vec<String> {
    strings(update_report, "held_out_boards")
}

/// Measurements step 1 held out of the updating while their boards were updated
/// (update_report.json's `held_out_measurements`; absent before the option).
pub fn held_out_measurements(update_report: &serde_json::Value) -> Vec<String> {
    strings(update_report, "held_out_measurements")
}

/// The strings of an array member of a JSON document (none where it is absent).
fn strings(v: &serde_json::Value, key: &str) -> Vec<String> {
    v.get(key)
        .and_then(|v| v.as_array())
        .into_iter()
        .flatten()
        .filter_map(|b| b.as_str().map(str::to_string))
        .collect()
}

/// The warnings and errors of a stage report's `findings`, as the report lists them.
pub fn findings_of(stage: &str, v: &serde_json::Value, out: &mut Vec<FindingRow>) {
    for f in v
        .get("findings")
        .and_then(|f| f.as_array())
        .into_iter()
        .flatten()
    {
        let sev = f.get("severity").and_then(|s| s.as_str()).unwrap_or("");
        if !matches!(sev, "warning" | "error") {
            continue;
        }
        let s = |k: &str| f.get(k).and_then(|x| x.as_str()).unwrap_or("").to_string();
        let mut w = vec![];
        for k in ["file", "measurement_id", "record"] {
            if !s(k).is_empty() {
                w.push(s(k));
            }
        }
        if let Some(l) = f.get("line").and_then(|l| l.as_u64()) {
            w.push(format!("line {l}"));
        }
        out.push(FindingRow {
            stage: stage.into(),
            severity: sev.into(),
            code: s("code"),
            where_: w.join(", "),
            message: s("message"),
        });
    }
}

/// What ingest_report.json says of the campaign: measurements, quarantined measurements
/// (id, reason) and the counts per kind.
#[derive(Debug, Default)]
pub struct IngestSummary {
    pub measurements: usize,
    pub quarantined: Vec<(String, String)>,
    pub counts: BTreeMap<String, u64>,
}

/// [`IngestSummary`] of an ingest report (a quarantined entry is an id or an object with
/// `measurement_id` and `reason`).
pub fn ingest_summary(v: &serde_json::Value) -> IngestSummary {
    let mut out = IngestSummary {
        measurements: v.get("measurements").and_then(|x| x.as_u64()).unwrap_or(0) as usize,
        ..IngestSummary::default()
    };
    for q in v
        .get("quarantined")
        .and_then(|x| x.as_array())
        .into_iter()
        .flatten()
    {
        let s = |k: &str| q.get(k).and_then(|x| x.as_str()).unwrap_or("").to_string();
        let id = if q.is_string() {
            q.as_str().unwrap_or("").to_string()
        } else {
            s("measurement_id")
        };
        out.quarantined.push((id, s("reason")));
    }
    if let Some(o) = v.get("counts").and_then(|x| x.as_object()) {
        for (k, c) in o {
            out.counts.insert(k.clone(), c.as_u64().unwrap_or(0));
        }
    }
    out
}

/// The report's note on a missing step-2 posterior; `note` is step 2's update_report.json
/// when it ran and found nothing to update (its `update.no_bolted_data` finding says why).
pub fn step2_absent(note: Option<&serde_json::Value>) -> String {
    let why = match note {
        Some(v) => v
            .get("findings")
            .and_then(|f| f.as_array())
            .and_then(|f| f.iter().find(|f| f["code"] == "update.no_bolted_data"))
            .and_then(|f| f["message"].as_str())
            .map(|m| format!("step 2 ran and found nothing to update: {m}. "))
            .unwrap_or_default(),
        None => String::new(),
    };
    format!(
        "{why}The work directory has no step-2 posterior (update_joints/joints.parquet): the joints were not updated, so there are no bolted predictions, no bolted Table-2 rows or boxes, and no joint posterior in this report."
    )
}

/// A copied plot's link: (measurement, what, path under the report) from the stage that drew
/// it (`extract`, `pair`) and its file name `<measurement>_<what>.svg`.
pub fn plot_link(kind: &str, name: &str) -> (String, String, String) {
    let rel = format!("plots/{kind}/{name}");
    let (mid, what) = match name.strip_suffix(".svg").and_then(|s| s.rsplit_once('_')) {
        Some((m, k)) => (m.to_string(), k.to_string()),
        None => (name.to_string(), kind.to_string()),
    };
    (mid, what, rel)
}
