//! Parquet tables: column specifications (name, type, unit, meaning), Arrow schemas built from
//! them, the writer that stamps units and provenance into both the Arrow schema metadata and
//! the Parquet file metadata, and the JSON documentation of each table under `schemas/tables/`.
//!
//! The [`TableSpec`]s (here for ingest and `fe`, in their stage files for `extract` and `pair`)
//! are the single source of truth: `schemas/tables/*.json` are generated from them (`hbmu schemas --out schemas`) and a test fails when the checked-in files
//! drift. Columns are flat and pandas-friendly: scalars, strings, and `list<float64>` for
//! spectra and shapes (pyarrow turns those into numpy arrays per cell). No `pandas` metadata
//! key is written: pandas reconstructs the frame from the Arrow schema alone.

pub mod diagnose;
pub mod extract;
pub mod fe;
pub mod pairs;
pub mod propagate;
pub mod report;
pub mod update;

use arrow::array::{ArrayRef, RecordBatch};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use serde_json::json;
use std::collections::{BTreeMap, HashMap};
use std::io;
use std::path::Path;
use std::sync::Arc;

pub use crate::table_spec::{c, Col, ColumnSpec, TableSpec};

impl Col {
    pub fn arrow(self) -> DataType {
        match self {
            Col::Utf8 => DataType::Utf8,
            Col::Int32 => DataType::Int32,
            Col::Int64 => DataType::Int64,
            Col::Float64 => DataType::Float64,
            Col::Bool => DataType::Boolean,
            Col::ListF64 => DataType::List(Arc::new(Field::new("item", DataType::Float64, true))),
            Col::ListI64 => DataType::List(Arc::new(Field::new("item", DataType::Int64, true))),
        }
    }
    fn name(self) -> &'static str {
        match self {
            Col::Utf8 => "string",
            Col::Int32 => "int32",
            Col::Int64 => "int64",
            Col::Float64 => "float64",
            Col::Bool => "bool",
            Col::ListF64 => "list<float64>",
            Col::ListI64 => "list<int64>",
        }
    }
    fn json_type(self) -> serde_json::Value {
        match self {
            Col::Utf8 => json!("string"),
            Col::Int32 | Col::Int64 => json!("integer"),
            Col::Float64 => json!("number"),
            Col::Bool => json!("boolean"),
            Col::ListF64 => json!({"type": "array", "items": {"type": "number"}}),
            Col::ListI64 => json!({"type": "array", "items": {"type": "integer"}}),
        }
    }
}

impl TableSpec {
    /// Arrow schema with per-field metadata (`unit`, `doc`) and the given table metadata.
    pub fn schema(&self, extra: &[Field], metadata: &BTreeMap<String, String>) -> SchemaRef {
        let mut fields: Vec<Field> = self
            .columns
            .iter()
            .map(|c| {
                let mut md = HashMap::new();
                if !c.unit.is_empty() {
                    md.insert("unit".to_string(), c.unit.to_string());
                }
                Field::new(c.name, c.ty.arrow(), c.nullable).with_metadata(md)
            })
            .collect();
        fields.extend(extra.iter().cloned());
        Arc::new(Schema::new_with_metadata(
            fields,
            metadata
                .iter()
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect::<HashMap<String, String>>(),
        ))
    }

    /// `{column: unit}` for the columns that have one.
    pub fn units(&self) -> BTreeMap<String, String> {
        self.columns
            .iter()
            .filter(|c| !c.unit.is_empty())
            .map(|c| (c.name.to_string(), c.unit.to_string()))
            .collect()
    }

    /// JSON Schema (draft 2020-12) of one row, with `x-arrow-type` and `x-unit` annotations.
    pub fn json_schema(&self) -> serde_json::Value {
        let mut props = serde_json::Map::new();
        for c in self.columns {
            let ty = c.ty.json_type();
            let ty = if c.nullable {
                json!({"anyOf": [ty_to_schema(&ty), {"type": "null"}]})
            } else {
                ty_to_schema(&ty)
            };
            let mut o = ty.as_object().cloned().unwrap_or_default();
            o.insert("description".into(), json!(c.doc));
            o.insert("x-arrow-type".into(), json!(c.ty.name()));
            if !c.unit.is_empty() {
                o.insert("x-unit".into(), json!(c.unit));
            }
            props.insert(c.name.into(), serde_json::Value::Object(o));
        }
        json!({
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "$id": format!("hbmu/tables/{}.json", self.name),
            "title": format!("{}.parquet (one row)", self.name),
            "description": self.doc,
            "type": "object",
            "properties": props,
            "required": self.columns.iter().filter(|c| !c.nullable).map(|c| c.name).collect::<Vec<_>>(),
            "additionalProperties": self.open,
        })
    }
}

fn ty_to_schema(ty: &serde_json::Value) -> serde_json::Value {
    if ty.is_string() {
        json!({ "type": ty })
    } else {
        ty.clone()
    }
}

/// Provenance and units stamped into every table we write.
pub fn table_metadata(
    spec: &TableSpec,
    provenance: &BTreeMap<String, String>,
) -> BTreeMap<String, String> {
    let mut md = provenance.clone();
    md.insert("hbmu.table".into(), spec.name.into());
    md.insert(
        "hbmu.units".into(),
        serde_json::to_string(&spec.units()).expect("map of strings serialises"),
    );
    md
}

/// Write one record batch as a Parquet file, atomically, with the schema's metadata copied into
/// the Parquet footer's key-value metadata too (pyarrow does not always carry one into the
/// other). Deterministic: no timestamps, one writer thread, fixed compression level.
pub fn write_parquet(path: &Path, batch: &RecordBatch) -> io::Result<()> {
    let kv: Vec<KeyValue> = batch
        .schema()
        .metadata()
        .iter()
        .collect::<BTreeMap<_, _>>()
        .into_iter()
        .map(|(k, v)| KeyValue::new(k.clone(), v.clone()))
        .collect();
    // Dictionary encoding pays off for strings (ids, labels) and costs time for nothing on
    // spectra and coordinates: enable it for string columns only.
    let mut builder = WriterProperties::builder().set_dictionary_enabled(false);
    for f in batch.schema().fields() {
        if f.data_type() == &DataType::Utf8 {
            builder = builder.set_column_dictionary_enabled(
                parquet::schema::types::ColumnPath::from(f.name().as_str()),
                true,
            );
        }
        // Spectra (list<float64>) are nearly all the bytes of a campaign, noise in their low
        // mantissa bits: byte-stream-split puts the sign/exponent bytes together, where zstd
        // level 1 compresses them. On the lab's paper campaign this wrote frf.parquet in
        // 0.45-0.50 s and 86.4 MB, against 0.83 s and 101.1 MB with plain zstd level 3.
        if let DataType::List(item) = f.data_type() {
            if item.data_type() == &DataType::Float64 {
                let col = parquet::schema::types::ColumnPath::new(vec![
                    f.name().clone(),
                    "list".into(),
                    item.name().clone(),
                ]);
                builder = builder
                    .set_column_compression(
                        col.clone(),
                        Compression::ZSTD(ZstdLevel::try_new(1).map_err(io::Error::other)?),
                    )
                    .set_column_encoding(col, parquet::basic::Encoding::BYTE_STREAM_SPLIT);
            }
        }
    }
    let props = builder
        .set_compression(Compression::ZSTD(
            ZstdLevel::try_new(3).map_err(io::Error::other)?,
        ))
        .set_key_value_metadata(Some(kv))
        .set_created_by(format!("hbmu {}", crate::io::manifest::TOOL_VERSION))
        .build();
    crate::io::atomic::write_with(path, |w| {
        let mut writer =
            ArrowWriter::try_new(w, batch.schema(), Some(props)).map_err(io::Error::other)?;
        writer.write(batch).map_err(io::Error::other)?;
        writer.close().map_err(io::Error::other)?;
        Ok(())
    })
}

/// A `list<float64>` column, one list per row.
pub fn list_f64_col<I: IntoIterator<Item = Vec<f64>>>(rows: I) -> ArrayRef {
    let mut b = arrow::array::ListBuilder::new(arrow::array::Float64Builder::new());
    for v in rows {
        b.values().append_slice(&v);
        b.append(true);
    }
    Arc::new(b.finish())
}

/// A `list<int64>` column, one list per row.
pub fn list_i64_col<I: IntoIterator<Item = Vec<i64>>>(rows: I) -> ArrayRef {
    let mut b = arrow::array::ListBuilder::new(arrow::array::Int64Builder::new());
    for v in rows {
        b.values().append_slice(&v);
        b.append(true);
    }
    Arc::new(b.finish())
}

/// Assemble a batch from columns in spec order (plus extra columns), checking lengths.
pub fn batch(schema: SchemaRef, columns: Vec<ArrayRef>) -> io::Result<RecordBatch> {
    RecordBatch::try_new(schema, columns).map_err(io::Error::other)
}

// ---------------------------------------------------------------------------------------------
// The ingest tables.

pub const MEASUREMENTS: TableSpec = TableSpec {
    name: "measurements",
    doc: "One row per sheet row (measurement): the sheet's columns, the ingest status, and a summary of its UFF file. Extra sheet columns follow as string columns with their header names (prefixed `sheet_` if they collide with a column here).",
    open: true,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id from the sheet."),
        c("board_id", Col::Utf8, false, "", "Specimen id from the sheet."),
        c("setup", Col::Utf8, false, "", "`free` or `bolted` (as written when unknown; such rows are quarantined)."),
        c("file", Col::Utf8, false, "", "UFF path relative to the campaign directory."),
        c("bolt_set", Col::Utf8, true, "", "Bolt/nut set identifier (bolted only)."),
        c("torque_nm", Col::Float64, true, "N.m", "Nominal tightening torque."),
        c("temperature_c", Col::Float64, true, "degC", "Lab temperature during the measurement."),
        c("date", Col::Utf8, true, "", "Date as written in the sheet (ISO-8601)."),
        c("date_unix_ns", Col::Int64, true, "ns", "Date as ns since the Unix epoch, UTC."),
        c("operator", Col::Utf8, true, "", "Operator (free text)."),
        c("notes", Col::Utf8, true, "", "Notes (free text)."),
        c("sheet_line", Col::Int64, false, "", "1-based line of the row in campaign.csv."),
        c("status", Col::Utf8, false, "", "`ok` or `quarantined`."),
        c("status_reason", Col::Utf8, true, "", "Why the measurement was quarantined."),
        c("function_type", Col::Int32, true, "", "UFF function type of the response records (4 FRF, 5 transmissibility)."),
        c("reference_node", Col::Int64, true, "", "Reference node (hammer impact point or shaker reference)."),
        c("n_scan_points", Col::Int32, false, "", "Scan points (nodes) in the file, reference node excluded."),
        c("n_records", Col::Int32, false, "", "Response records kept (function type 4 or 5)."),
        c("n_coherence", Col::Int32, false, "", "Coherence records kept (function type 6)."),
        c("n_records_dropped", Col::Int32, false, "", "Records dropped (see the ingest report)."),
        c("freq_start_hz", Col::Float64, true, "Hz", "First spectral line."),
        c("freq_step_hz", Col::Float64, true, "Hz", "Spectral line spacing."),
        c("n_lines", Col::Int32, true, "", "Number of spectral lines."),
        c("uff_blake3", Col::Utf8, true, "", "BLAKE3 hash of the UFF file."),
        c("length_mm", Col::Float64, true, "mm", "The specimen's measured length (along x), as the row gives it."),
        c("width_mm", Col::Float64, true, "mm", "The specimen's measured width (along y), as the row gives it."),
        c("thickness_mm", Col::Float64, true, "mm", "The specimen's measured overall thickness (over its copper layers, as a micrometer reads it), as the row gives it."),
    ],
};

pub const SCAN_POINTS: TableSpec = TableSpec {
    name: "scan_points",
    doc: "Scan-point geometry of each measurement, in the board frame (origin at a board corner, x along the long edge, z normal), converted to metres.",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id."),
        c("node", Col::Int64, false, "", "UFF node label."),
        c("x_m", Col::Float64, false, "m", "x coordinate."),
        c("y_m", Col::Float64, false, "m", "y coordinate."),
        c("z_m", Col::Float64, false, "m", "z coordinate."),
        c("is_reference", Col::Bool, false, "", "True for the excitation reference node (hammer point or shaker reference)."),
        c("has_record", Col::Bool, false, "", "True when a response record exists for this node."),
    ],
};

pub const VENDOR_MODES: TableSpec = TableSpec {
    name: "vendor_modes",
    doc: "Modes a lab's modal software identified and exported as UFF dataset 55 (one set per mode), one row per mode, ascending in frequency within a measurement. For a measurement with no response record these are its modes (extract passes them through, `source = uff55` in modes.parquet); beside FRFs they are kept for comparison and extract identifies from the FRFs. The shape is the component along the response direction (Z of the translations, or the scalar) at the nodes with coordinates, real-normalised like extract's (largest |component| = +1).",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id."),
        c("mode", Col::Int32, false, "", "Mode number in this measurement, 1-based, ascending frequency."),
        c("mode_number", Col::Int64, true, "", "The file's mode number (record 7), when given."),
        c("analysis_type", Col::Int32, false, "", "Dataset 55 analysis type: 2 normal mode, 3 or 7 complex mode."),
        c("uff_line", Col::Int64, false, "", "1-based line of the dataset in its UFF file."),
        c("freq_hz", Col::Float64, false, "Hz", "Undamped natural frequency (type 2: record 8; types 3/7: |lambda|/(2 pi))."),
        c("damping_ratio", Col::Float64, false, "", "Viscous damping ratio (type 2: record 8; types 3/7: -Re(lambda)/|lambda|)."),
        c("mpc", Col::Float64, false, "", "Modal phase collinearity of the shape, 0..1 (1 for a real shape)."),
        c("mpd_deg", Col::Float64, false, "deg", "Mean phase deviation of the shape."),
        c("node", Col::ListI64, false, "", "Nodes with a value and coordinates, ascending."),
        c("shape", Col::ListF64, false, "", "Real-normalised shape at `node`."),
    ],
};

pub const FRF: TableSpec = TableSpec {
    name: "frf",
    doc: "One row per function record (scan point x function type), spectra as list columns: one row per record keeps the table at thousands of rows instead of millions, and each cell becomes a numpy array in pandas. The frequency axis is evenly spaced and stored once per record, not per line: line k of `re`/`im` lies at `freq_start_hz + k * freq_step_hz`, k = 0..n_lines-1 (pandas: `frf[\"freq_hz\"] = [r.freq_start_hz + r.freq_step_hz * np.arange(r.n_lines) for r in frf.itertuples()]`, then `frf[frf.function_type != 6].explode([\"freq_hz\",\"re\",\"im\"])` gives the long form of the responses). Ordinates in SI: mobility (m/s)/N for type 4 and a velocity ratio for 5 (transmissibility), whatever the lab measured (`measured_as`; an accelerance is divided by iω); type 6 is coherence (`im` null). Tables written before layout 2 had a `freq_hz` list column instead of the three axis columns; readers refuse them with a message to re-run ingest.",
    open: false,
    columns: &[
        c("measurement_id", Col::Utf8, false, "", "Measurement id."),
        c("node", Col::Int64, false, "", "Response node."),
        c("function_type", Col::Int32, false, "", "4 FRF, 5 transmissibility, 6 coherence."),
        c("response_direction", Col::Int32, false, "", "UFF direction code of the response (3 = +Z)."),
        c("reference_node", Col::Int64, false, "", "Reference node."),
        c("reference_direction", Col::Int32, false, "", "UFF direction code of the reference."),
        c("ordinate_unit", Col::Utf8, false, "", "Unit of re/im: `m/s/N`, `1`."),
        c("measured_as", Col::Utf8, false, "", "What the lab measured, numerator/denominator (`velocity/force` mobility, `acceleration/force` accelerance, `displacement/force` receptance, `acceleration/acceleration`, ...; `coherence`; `unspecified` when the file names no motion and the contract's quantity is assumed). re/im are converted to ordinate_unit by (iω)^q, ω = 2πf."),
        c("freq_start_hz", Col::Float64, false, "Hz", "Frequency of the first spectral line."),
        c("freq_step_hz", Col::Float64, false, "Hz", "Spacing of the spectral lines."),
        c("n_lines", Col::Int32, false, "", "Number of spectral lines (length of re and im)."),
        c("re", Col::ListF64, false, "", "Real part (unit in ordinate_unit)."),
        c("im", Col::ListF64, true, "", "Imaginary part; null for real functions (coherence)."),
    ],
};

pub const SCALE_READINGS: TableSpec = TableSpec {
    name: "scale_readings",
    doc: "Every balance log line (comments and blank lines excepted) with its parsed MT-SICS status.",
    open: false,
    columns: &[
        c("file", Col::Utf8, false, "", "Log file relative to the campaign directory."),
        c("line", Col::Int64, false, "", "1-based line."),
        c("timestamp", Col::Utf8, true, "", "Timestamp as written."),
        c("time_unix_ns", Col::Int64, true, "ns", "Timestamp as ns since the Unix epoch, UTC."),
        c("board_id", Col::Utf8, true, "", "ID as written in the log (a board, or a check weight, a tray...)."),
        c("sheet_board_id", Col::Utf8, true, "", "The sheet's board the line counts for (its board_id resolved against the sheet); null when the ID is not a board of the sheet or is ambiguous."),
        c("response", Col::Utf8, false, "", "MT-SICS response as written."),
        c("status", Col::Utf8, false, "", "stable, dynamic, busy, overload, underload, zeroed, tared, syntax_error, transmission_error, logic_error, unparsed."),
        c("value", Col::Float64, true, "", "Value as printed, in `unit`."),
        c("unit", Col::Utf8, true, "", "g, mg or kg."),
        c("mass_g", Col::Float64, true, "g", "Value in grams."),
        c("resolution_g", Col::Float64, true, "g", "Readability inferred from the printed decimals."),
    ],
};

pub const MASSES: TableSpec = TableSpec {
    name: "masses",
    doc: "Masses of the sheet's boards from their stable balance readings only; an ID that is not a board of the sheet has no row.",
    open: false,
    columns: &[
        c("board_id", Col::Utf8, false, "", "Board."),
        c(
            "mass_g",
            Col::Float64,
            false,
            "g",
            "Mean of the stable readings.",
        ),
        c(
            "n_stable",
            Col::Int32,
            false,
            "",
            "Number of stable readings.",
        ),
        c(
            "std_g",
            Col::Float64,
            false,
            "g",
            "Sample standard deviation of the stable readings (0 for one reading).",
        ),
        c(
            "resolution_g",
            Col::Float64,
            false,
            "g",
            "Balance readability inferred from the printed decimals.",
        ),
        c(
            "inconsistent",
            Col::Bool,
            false,
            "",
            "True when the readings disagree more than the resolution suggests (std > 3 d).",
        ),
        c(
            "n_days",
            Col::Int32,
            false,
            "",
            "Days (timestamp dates) with a stable reading.",
        ),
        c(
            "day_means_ss_g2",
            Col::Float64,
            false,
            "g²",
            "Sum of squares of the board's per-day mean readings about their mean (n_days - 1 degrees of freedom; 0 for one day): what re-placing the board changes. update pools it over the boards into the balance's placement scatter.",
        ),
        c(
            "day_share_sq_sum",
            Col::Float64,
            false,
            "",
            "Sum over the days of (the day's share of the stable readings)²: mass_g's variance is one day mean's times this (1 for one day).",
        ),
    ],
};

pub const SPECIMENS: TableSpec = TableSpec {
    name: "specimens",
    doc: "Every board of the sheet with its measured dimensions (the sheet's optional length_mm, width_mm, thickness_mm): the mean over the rows that give one, null where none does. update takes thickness_mm less the board file's copper layers as a measurement of the board's core thickness.",
    open: false,
    columns: &[
        c("board_id", Col::Utf8, false, "", "Board."),
        c("length_mm", Col::Float64, true, "mm", "Measured length (along x)."),
        c("width_mm", Col::Float64, true, "mm", "Measured width (along y)."),
        c("thickness_mm", Col::Float64, true, "mm", "Measured overall thickness (the core plus the copper layers; update takes the board file's copper off)."),
        c("n_rows_length", Col::Int32, false, "", "Sheet rows giving the length."),
        c("n_rows_width", Col::Int32, false, "", "Sheet rows giving the width."),
        c("n_rows_thickness", Col::Int32, false, "", "Sheet rows giving the thickness."),
    ],
};

/// Every table spec the tool writes (for `hbmu schemas` and the drift test).
pub fn all_tables() -> Vec<&'static TableSpec> {
    vec![
        &MEASUREMENTS,
        &SCAN_POINTS,
        &FRF,
        &VENDOR_MODES,
        &SCALE_READINGS,
        &MASSES,
        &SPECIMENS,
        &FE_MODES,
        &SENSITIVITY,
    ]
}

// ---------------------------------------------------------------------------------------------
// The physics-core tables (`hbmu fe …`).

pub const FE_MODES: TableSpec = TableSpec {
    name: "fe_modes",
    doc: "Modes of the full FE model, one row per elastic mode (rigid-body modes removed), with the out-of-plane shape at a point set (the board's scan grid or a measurement's scan points). Shapes are mass-normalised (phi^T M phi = 1).",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("mode", Col::Int32, false, "", "Mode number, 1-based, ascending frequency."),
        c("freq_hz", Col::Float64, false, "Hz", "Natural frequency."),
        c("node", Col::ListI64, false, "", "Point ids (scan-point node labels, or 1..n for the board grid)."),
        c("x_m", Col::ListF64, false, "m", "Point x coordinates."),
        c("y_m", Col::ListF64, false, "m", "Point y coordinates."),
        c("shape_w", Col::ListF64, false, "1/sqrt(kg)", "Out-of-plane displacement of the mass-normalised mode at the points."),
    ],
};

pub const SENSITIVITY: TableSpec = TableSpec {
    name: "sensitivity",
    doc: "Relative eigenfrequency sensitivities (p/f) df/dp in %/% at the nominal parameters (the analog of the seed paper's Table 1), one row per mode and parameter, from analytic eigenvalue derivatives.",
    open: false,
    columns: &[
        c("setup", Col::Utf8, false, "", "`free` or `bolted`."),
        c("mode", Col::Int32, false, "", "Mode number, 1-based."),
        c("freq_hz", Col::Float64, false, "Hz", "Natural frequency at the nominal parameters."),
        c("param", Col::Utf8, false, "", "Parameter name (unit in the name)."),
        c("value", Col::Float64, false, "", "Nominal parameter value (unit in the parameter name)."),
        c("d_freq_hz_per_unit", Col::Float64, false, "", "df/dp, Hz per parameter unit."),
        c("pct_per_pct", Col::Float64, false, "%/%", "(p/f) df/dp."),
    ],
};

// ---------------------------------------------------------------------------------------------
// Readers for the tables other stages consume.

use arrow::array::{Array, AsArray};
use arrow::datatypes::{Float64Type, Int64Type};

/// Read every batch of a Parquet file.
pub fn read_parquet(path: &Path) -> io::Result<Vec<RecordBatch>> {
    let file = std::fs::File::open(path)
        .map_err(|e| io::Error::new(e.kind(), format!("{}: {e}", path.display())))?;
    let reader = parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder::try_new(file)
        .map_err(|e| io::Error::other(format!("{}: {e}", path.display())))?
        .build()
        .map_err(|e| io::Error::other(format!("{}: {e}", path.display())))?;
    reader
        .map(|b| b.map_err(|e| io::Error::other(format!("{}: {e}", path.display()))))
        .collect()
}

fn column<'a>(b: &'a RecordBatch, name: &str, path: &Path) -> io::Result<&'a ArrayRef> {
    b.column_by_name(name).ok_or_else(|| {
        io::Error::other(format!(
            "{}: expected column {name:?} (see schemas/tables), not found",
            path.display()
        ))
    })
}

/// `frf.parquet` of layout 2 (frequency axis as start + step per record); a table of the
/// older layout (a `freq_hz` list per record) is refused with what to do.
pub fn check_frf_layout(b: &RecordBatch, path: &Path) -> io::Result<()> {
    if b.column_by_name("freq_start_hz").is_none() && b.column_by_name("freq_hz").is_some() {
        return Err(io::Error::other(format!(
            "{}: old frf.parquet layout (a freq_hz list per record, written before hbmu's frf \
             layout 2); this version stores the axis as freq_start_hz + freq_step_hz per record \
             (schemas/tables/frf.json): re-run `hbmu ingest CAMPAIGN --out DIR --force`",
            path.display()
        )));
    }
    Ok(())
}

/// Typed column accessors; errors name the file, column and expected type.
pub struct Cols<'a> {
    pub batch: &'a RecordBatch,
    pub path: &'a Path,
}

impl<'a> Cols<'a> {
    fn typed<T: 'static>(&self, name: &str, what: &str) -> io::Result<&'a T> {
        column(self.batch, name, self.path)?
            .as_any()
            .downcast_ref::<T>()
            .ok_or_else(|| {
                io::Error::other(format!(
                    "{}: column {name:?}: expected {what}",
                    self.path.display()
                ))
            })
    }
    pub fn str(&self, name: &str) -> io::Result<&'a arrow::array::StringArray> {
        self.typed(name, "string")
    }
    pub fn f64(&self, name: &str) -> io::Result<&'a arrow::array::Float64Array> {
        self.typed(name, "float64")
    }
    pub fn i64(&self, name: &str) -> io::Result<&'a arrow::array::Int64Array> {
        self.typed(name, "int64")
    }
    pub fn i32(&self, name: &str) -> io::Result<&'a arrow::array::Int32Array> {
        self.typed(name, "int32")
    }
    pub fn bool(&self, name: &str) -> io::Result<&'a arrow::array::BooleanArray> {
        self.typed(name, "bool")
    }
    /// Row `i` of a `list<float64>` column (`None` when null).
    pub fn list_f64(&self, name: &str, i: usize) -> io::Result<Option<Vec<f64>>> {
        let col = column(self.batch, name, self.path)?;
        let l = col.as_list_opt::<i32>().ok_or_else(|| {
            io::Error::other(format!(
                "{}: column {name:?}: expected list<float64>",
                self.path.display()
            ))
        })?;
        if l.is_null(i) {
            return Ok(None);
        }
        let v = l.value(i);
        let p = v.as_primitive_opt::<Float64Type>().ok_or_else(|| {
            io::Error::other(format!(
                "{}: column {name:?}: expected list<float64>",
                self.path.display()
            ))
        })?;
        Ok(Some(p.values().to_vec()))
    }
    /// Row `i` of a `list<int64>` column.
    pub fn list_i64(&self, name: &str, i: usize) -> io::Result<Vec<i64>> {
        let col = column(self.batch, name, self.path)?;
        let l = col.as_list_opt::<i32>().ok_or_else(|| {
            io::Error::other(format!(
                "{}: column {name:?}: expected list<int64>",
                self.path.display()
            ))
        })?;
        let v = l.value(i);
        let p = v.as_primitive_opt::<Int64Type>().ok_or_else(|| {
            io::Error::other(format!(
                "{}: column {name:?}: expected list<int64>",
                self.path.display()
            ))
        })?;
        Ok(p.values().to_vec())
    }
}

/// One scan point read back from `scan_points.parquet`.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanPointRow {
    pub measurement_id: String,
    pub node: i64,
    pub xyz_m: [f64; 3],
    pub is_reference: bool,
    pub has_record: bool,
}

/// Read `scan_points.parquet`.
pub fn read_scan_points(path: &Path) -> io::Result<Vec<ScanPointRow>> {
    let mut out = Vec::new();
    for b in read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (m, n, x, y, z, r, h) = (
            c.str("measurement_id")?,
            c.i64("node")?,
            c.f64("x_m")?,
            c.f64("y_m")?,
            c.f64("z_m")?,
            c.bool("is_reference")?,
            c.bool("has_record")?,
        );
        for i in 0..b.num_rows() {
            out.push(ScanPointRow {
                measurement_id: m.value(i).to_string(),
                node: n.value(i),
                xyz_m: [x.value(i), y.value(i), z.value(i)],
                is_reference: r.value(i),
                has_record: h.value(i),
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn old_frf_layout_is_refused_with_what_to_do() {
        let old = RecordBatch::try_from_iter(vec![
            (
                "node",
                Arc::new(arrow::array::Int64Array::from(vec![1])) as ArrayRef,
            ),
            ("freq_hz", list_f64_col([vec![1.0, 2.0]])),
        ])
        .unwrap();
        let e = check_frf_layout(&old, Path::new("w/ingest/frf.parquet")).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("w/ingest/frf.parquet") && msg.contains("old frf.parquet layout"));
        assert!(msg.contains("hbmu ingest"), "{msg}");
        let new = RecordBatch::try_from_iter(vec![
            (
                "freq_start_hz",
                Arc::new(arrow::array::Float64Array::from(vec![0.0])) as ArrayRef,
            ),
            (
                "freq_step_hz",
                Arc::new(arrow::array::Float64Array::from(vec![1.0])) as ArrayRef,
            ),
        ])
        .unwrap();
        assert!(check_frf_layout(&new, Path::new("frf.parquet")).is_ok());
    }
}
