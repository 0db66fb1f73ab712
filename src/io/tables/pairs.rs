//! The spec, row types, reader and writer of pair's pairs.parquet and presence.parquet.

use crate::io::tables::{self, c, Col, Cols, TableSpec};
use crate::modal::pair::{LabelPresence, MeasurementModes, PairRecord};
use arrow::array::{Array, ArrayRef, BooleanArray, Float64Array, Int32Array, StringArray};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

pub const PAIRS: TableSpec = TableSpec {
    name: "pairs",
    doc: "Pairing of identified modes with model modes per measurement. One row per identified mode (model_mode null when unpaired) plus one row per model mode in the band that found no partner (mode null, `missing` true).",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id."),
        c("board_id", Col::Utf8, false, "", "Board."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("mode", Col::Int32, true, "", "Identified mode number (as in modes.parquet); null for a missing model mode."),
        c("freq_hz", Col::Float64, true, "Hz", "Identified frequency."),
        c("model_mode", Col::Int32, true, "", "Model mode number, 1-based; null when unpaired."),
        c("model_freq_hz", Col::Float64, true, "Hz", "Model frequency at nominal parameters."),
        c("label", Col::Utf8, false, "", "Label derived from the model shape (e.g. torsion-1, bending-x-1)."),
        c("mac", Col::Float64, true, "", "MAC between the identified and the model shape."),
        c("accepted", Col::Bool, false, "", "Pair passes the MAC and frequency thresholds."),
        c("missing", Col::Bool, false, "", "A model mode in the band with no accepted partner."),
        c("swapped", Col::Bool, false, "", "The pair's order differs from the model's frequency order (mode swap)."),
    ],
};

pub const PRESENCE: TableSpec = TableSpec {
    name: "presence",
    doc: "The presence rule: per setup and mode label, in how many measurements the mode was accepted, and whether it counts for updating (present in at least `min_fraction` of the setup's measurements; the paper: every measurement).",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("label", Col::Utf8, false, "", "Mode label."),
        c("n_present", Col::Int32, false, "", "Measurements of the setup in which the mode was accepted."),
        c("n_measurements", Col::Int32, false, "", "Measurements of the setup."),
        c("used_for_updating", Col::Bool, false, "", "n_present >= min_fraction * n_measurements."),
    ],
};

pub use crate::modal::rows::PairRow;

/// The accepted pairs of pairs.parquet (with an identified mode, a frequency and a model mode).
pub fn read_pairs(path: &Path) -> anyhow::Result<Vec<PairRow>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (mid, bid, setup, mode, f, mm, label, acc) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.i32("mode")?,
            c.f64("freq_hz")?,
            c.i32("model_mode")?,
            c.str("label")?,
            c.bool("accepted")?,
        );
        for i in 0..b.num_rows() {
            if !acc.value(i) || mode.is_null(i) || f.is_null(i) || mm.is_null(i) {
                continue;
            }
            out.push(PairRow {
                measurement_id: mid.value(i).into(),
                board_id: bid.value(i).into(),
                setup: setup.value(i).into(),
                mode: mode.value(i),
                freq_hz: f.value(i),
                model_mode: mm.value(i),
                label: label.value(i).into(),
            });
        }
    }
    Ok(out)
}

/// The labels of presence.parquet used for updating in `setup`, in file order.
pub fn read_presence(path: &Path, setup: &str) -> anyhow::Result<Vec<String>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (s, l, u) = (
            c.str("setup")?,
            c.str("label")?,
            c.bool("used_for_updating")?,
        );
        for i in 0..b.num_rows() {
            if s.value(i) == setup && u.value(i) {
                out.push(l.value(i).to_string());
            }
        }
    }
    Ok(out)
}

/// Write pairs.parquet at `path`.
pub fn write_pairs(
    path: &Path,
    prov: &BTreeMap<String, String>,
    rows: &[(&MeasurementModes, PairRecord)],
) -> anyhow::Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|(m, _)| m.measurement_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|(m, _)| m.board_id.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|(m, _)| m.setup.as_str()),
        )),
        Arc::new(Int32Array::from_iter(rows.iter().map(|(_, r)| r.mode))),
        Arc::new(Float64Array::from_iter(rows.iter().map(|(_, r)| r.freq_hz))),
        Arc::new(Int32Array::from_iter(
            rows.iter().map(|(_, r)| r.model_mode),
        )),
        Arc::new(Float64Array::from_iter(
            rows.iter().map(|(_, r)| r.model_freq_hz),
        )),
        Arc::new(StringArray::from_iter_values(
            rows.iter().map(|(_, r)| r.label.as_str()),
        )),
        Arc::new(Float64Array::from_iter(rows.iter().map(|(_, r)| r.mac))),
        Arc::new(BooleanArray::from_iter(
            rows.iter().map(|(_, r)| Some(r.accepted)),
        )),
        Arc::new(BooleanArray::from_iter(
            rows.iter().map(|(_, r)| Some(r.missing)),
        )),
        Arc::new(BooleanArray::from_iter(
            rows.iter().map(|(_, r)| Some(r.swapped)),
        )),
    ];
    let schema = PAIRS.schema(&[], &tables::table_metadata(&PAIRS, prov));
    tables::write_parquet(path, &tables::batch(schema, cols)?)?;
    Ok(())
}

/// Write presence.parquet at `path`.
pub fn write_presence(
    path: &Path,
    prov: &BTreeMap<String, String>,
    present: &[LabelPresence],
) -> anyhow::Result<()> {
    let cols: Vec<ArrayRef> = vec![
        Arc::new(StringArray::from_iter_values(
            present.iter().map(|r| r.setup.as_str()),
        )),
        Arc::new(StringArray::from_iter_values(
            present.iter().map(|r| r.label.as_str()),
        )),
        Arc::new(Int32Array::from_iter_values(
            present.iter().map(|r| r.n_present as i32),
        )),
        Arc::new(Int32Array::from_iter_values(
            present.iter().map(|r| r.n_measurements as i32),
        )),
        Arc::new(BooleanArray::from_iter(
            present.iter().map(|r| Some(r.used_for_updating)),
        )),
    ];
    let schema = PRESENCE.schema(&[], &tables::table_metadata(&PRESENCE, prov));
    tables::write_parquet(path, &tables::batch(schema, cols)?)?;
    Ok(())
}
