//! Universal File Format (UFF) reading and writing: the types of the datasets a modal-test
//! campaign uses (58/58b functions at nodal DOF, 55 mode sets, 2411/15 nodes, 164 units), the byte-level
//! parser [`parse`] that returns every good dataset plus a list of issues for the bad ones, and
//! the fixed-width writers [`write_58`], [`write_2411`], [`write_15`], [`write_164`].
//!
//! Written by hand because no Rust crate reads or writes UFF. The formats follow the SDRC/I-DEAS
//! dataset descriptions (as reproduced by the Python package `pyuff`, which is the reference our
//! interop tests check against). The parser never does file I/O and never panics: every malformed
//! input becomes an [`UffIssue`] (bad dataset, others still returned) or an [`UffError`] (the
//! bytes are not a UFF at all).

mod ascii;
mod binary;
mod ds55;
mod read;
mod write;

#[cfg(test)]
mod tests;

pub use read::parse;
pub use write::{write_15, write_164, write_2411, write_58, Format, UffWriteError};

/// One parsed file: the datasets that were read, in file order, the datasets that were
/// malformed (one issue each), and the datasets of a type this reader does not decode.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct UffFile {
    pub datasets: Vec<Dataset>,
    pub issues: Vec<UffIssue>,
    pub skipped: Vec<SkippedDataset>,
}

/// A decoded dataset.
#[derive(Debug, Clone, PartialEq)]
#[allow(
    clippy::large_enum_variant,
    reason = "a file holds tens of datasets whose bulk is on the heap; boxing saves nothing"
)]
pub enum Dataset {
    Units(Units164),
    Nodes(NodeSet),
    Function(Function58),
    NodalData(NodalData55),
}

/// A dataset of a number this reader does not decode (listed, never fatal).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SkippedDataset {
    /// UFF dataset number, e.g. 2412.
    pub number: u32,
    /// 1-based line of the dataset's opening `-1` delimiter.
    pub line: usize,
    /// 0-based position of the dataset among all datasets of the file.
    pub index: usize,
}

/// A dataset that could not be read. The other datasets of the file are unaffected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("line {line}: dataset {} (#{index} in file): {kind}", number_text(*.number))]
pub struct UffIssue {
    /// 1-based line where the problem was found.
    pub line: usize,
    /// UFF dataset number, if its number line could be read.
    pub number: Option<u32>,
    /// 0-based position of the dataset among all datasets of the file (for
    /// [`IssueKind::StrayText`], which belongs to no dataset: the position the next one takes).
    pub index: usize,
    pub kind: IssueKind,
}

fn number_text(n: Option<u32>) -> String {
    n.map_or_else(|| "?".to_owned(), |n| n.to_string())
}

/// What was wrong with a dataset: each variant says what was expected and what was found.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum IssueKind {
    #[error("dataset number line: expected an integer dataset number, found {found:?}")]
    BadNumberLine { found: String },
    #[error("record {record}, {field}: expected {expected}, found {found:?}")]
    BadField {
        record: usize,
        field: &'static str,
        expected: &'static str,
        found: String,
    },
    #[error("ordinate data type: expected 2, 4, 5 or 6, found {found}")]
    UnknownOrdinateDataType { found: i64 },
    #[error("abscissa spacing: expected 0 (uneven) or 1 (even), found {found}")]
    UnknownSpacing { found: i64 },
    #[error("data values: expected {expected} ({points} points), found {found}")]
    WrongValueCount {
        expected: usize,
        points: usize,
        found: usize,
    },
    #[error("data value {value_index}: expected a number, found {found:?}")]
    NonNumeric { value_index: usize, found: String },
    #[error("ordinate at point {point}: expected a finite number, found {value}")]
    NonFiniteOrdinate { point: usize, value: f64 },
    #[error("truncated: expected {expected}, found {found}")]
    Truncated { expected: String, found: String },
    #[error("binary header: expected {expected}, found {found:?}")]
    BadBinaryHeader {
        expected: &'static str,
        found: String,
    },
    #[error("text between datasets: expected a `-1` delimiter, found {found:?}")]
    StrayText { found: String },
}

/// Units, dataset 164. The factors convert file units to SI by division:
/// `value_SI = value_file / factor` (e.g. `length_factor = 1000` for millimetres).
#[derive(Debug, Clone, PartialEq)]
pub struct Units164 {
    /// 1 SI, 2 BG, 3 MG, 4 BA, 5 MM, 6 CM, 7 IN, 8 GM, 9 user defined.
    pub units_code: i32,
    pub description: String,
    /// 1 absolute, 2 relative.
    pub temperature_mode: i32,
    pub length_factor: f64,
    pub force_factor: f64,
    pub temperature_factor: f64,
    pub temperature_offset: f64,
    /// 1-based line of the opening `-1`.
    pub line: usize,
}

impl Units164 {
    /// Converts a length in file units to metres (UFF convention: SI = value / factor).
    pub fn length_to_metres(&self, length_file_units: f64) -> f64 {
        length_file_units / self.length_factor
    }

    /// Converts a force in file units to newtons (SI = value / factor).
    pub fn force_to_newtons(&self, force_file_units: f64) -> f64 {
        force_file_units / self.force_factor
    }
}

/// Which dataset a node set came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NodeSource {
    /// Dataset 2411 (nodes, double precision).
    Ds2411,
    /// Dataset 15 (nodes, single precision, older).
    Ds15,
}

impl NodeSource {
    pub fn number(self) -> u32 {
        match self {
            NodeSource::Ds2411 => 2411,
            NodeSource::Ds15 => 15,
        }
    }
}

/// Nodes from dataset 2411 or 15.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeSet {
    pub source: NodeSource,
    pub nodes: Vec<Node>,
    /// 1-based line of the opening `-1`.
    pub line: usize,
}

/// One node. Coordinates are in the file's length unit (see [`Units164::length_to_metres`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Node {
    pub id: i64,
    pub def_cs: i64,
    pub disp_cs: i64,
    pub color: i64,
    pub xyz_file_units: [f64; 3],
}

/// Function type of dataset 58 (record 6 field 1). Types this project uses have names; every
/// other code is kept as-is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FunctionType {
    /// 4: frequency response function.
    Frf,
    /// 5: transmissibility.
    Transmissibility,
    /// 6: coherence.
    Coherence,
    /// Any other code (0 general, 1 time response, 2 auto spectrum, 9 PSD, ...).
    Other(i64),
}

impl FunctionType {
    pub fn from_code(code: i64) -> Self {
        match code {
            4 => FunctionType::Frf,
            5 => FunctionType::Transmissibility,
            6 => FunctionType::Coherence,
            c => FunctionType::Other(c),
        }
    }
    pub fn code(self) -> i64 {
        match self {
            FunctionType::Frf => 4,
            FunctionType::Transmissibility => 5,
            FunctionType::Coherence => 6,
            FunctionType::Other(c) => c,
        }
    }
}

/// Ordinate data type of dataset 58 (record 7 field 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OrdinateDataType {
    /// 2: real, single precision.
    RealSingle,
    /// 4: real, double precision.
    RealDouble,
    /// 5: complex, single precision.
    ComplexSingle,
    /// 6: complex, double precision.
    ComplexDouble,
}

impl OrdinateDataType {
    pub fn from_code(code: i64) -> Option<Self> {
        match code {
            2 => Some(Self::RealSingle),
            4 => Some(Self::RealDouble),
            5 => Some(Self::ComplexSingle),
            6 => Some(Self::ComplexDouble),
            _ => None,
        }
    }
    pub fn code(self) -> i64 {
        match self {
            Self::RealSingle => 2,
            Self::RealDouble => 4,
            Self::ComplexSingle => 5,
            Self::ComplexDouble => 6,
        }
    }
    pub fn is_complex(self) -> bool {
        matches!(self, Self::ComplexSingle | Self::ComplexDouble)
    }
    pub fn is_double(self) -> bool {
        matches!(self, Self::RealDouble | Self::ComplexDouble)
    }
}

/// One axis description, records 8–11 of dataset 58.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct AxisSpec {
    /// Specific data type (0 unknown, 1 general, 2 stress, ... 18 frequency, ...).
    pub spec_data_type: i64,
    pub length_exp: i64,
    pub force_exp: i64,
    pub temperature_exp: i64,
    pub label: String,
    pub units_label: String,
}

/// Abscissa of a dataset-58 function, in the units of the abscissa axis (record 8).
#[derive(Debug, Clone, PartialEq)]
pub enum Abscissa {
    /// Evenly spaced: x_k = min + k · increment (not materialised).
    Even { min: f64, increment: f64 },
    /// Unevenly spaced: x values as read from the (x, y) pairs.
    Uneven(Vec<f64>),
}

/// Ordinate values, widened to f64 whatever the file precision.
#[derive(Debug, Clone, PartialEq)]
pub enum Ordinate {
    Real(Vec<f64>),
    Complex { re: Vec<f64>, im: Vec<f64> },
}

impl Ordinate {
    pub fn len(&self) -> usize {
        match self {
            Ordinate::Real(v) => v.len(),
            Ordinate::Complex { re, .. } => re.len(),
        }
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Dataset 58 (function at nodal DOF), ASCII or binary 58b, with every header field.
#[derive(Debug, Clone, PartialEq)]
pub struct Function58 {
    /// Records 1–5: ID lines (80 characters each), trailing blanks removed.
    pub id_lines: [String; 5],
    /// Record 6.
    pub function_type: FunctionType,
    pub function_id: i64,
    pub version: i64,
    pub load_case: i64,
    pub response_entity: String,
    pub response_node: i64,
    /// Direction code: 0 scalar, ±1 X, ±2 Y, ±3 Z, ±4..6 rotations.
    pub response_direction: i64,
    pub reference_entity: String,
    pub reference_node: i64,
    pub reference_direction: i64,
    /// Record 7.
    pub ordinate_data_type: OrdinateDataType,
    pub num_points: usize,
    pub z_axis_value: f64,
    /// Records 8–11.
    pub abscissa_axis: AxisSpec,
    pub ordinate_axis: AxisSpec,
    pub denominator_axis: AxisSpec,
    pub z_axis: AxisSpec,
    pub abscissa: Abscissa,
    pub ordinate: Ordinate,
    /// True if the data came from a binary 58b block.
    pub binary: bool,
    /// 1-based line of the opening `-1`.
    pub line: usize,
}

impl Function58 {
    /// Abscissa of point `k` (`min + k · increment` if even), `None` past the last point.
    pub fn abscissa_at(&self, k: usize) -> Option<f64> {
        if k >= self.num_points {
            return None;
        }
        match &self.abscissa {
            Abscissa::Even { min, increment } => Some(min + k as f64 * increment),
            Abscissa::Uneven(x) => x.get(k).copied(),
        }
    }
}

/// Dataset 55, data at nodes: in a modal test, one identified mode (its frequency and damping
/// in records 7–8, its shape at the nodes in records 9–10). Values are in the file's units.
#[derive(Debug, Clone, PartialEq)]
pub struct NodalData55 {
    /// Records 1–5, trailing blanks removed.
    pub id_lines: [String; 5],
    /// Record 6: 1 structural, ...
    pub model_type: i64,
    /// 2 normal mode, 3 complex eigenvalue first order, 7 second order, 5 frequency
    /// response, ...
    pub analysis_type: i64,
    /// 1 scalar, 2 three translations, 3 three translations and three rotations, ...
    pub data_characteristic: i64,
    /// 8 displacement, 11 velocity, 12 acceleration, ...
    pub specific_data_type: i64,
    /// Data type 5 (complex) rather than 2 (real).
    pub complex: bool,
    /// NDV: values per node (3 for translations X, Y, Z; 6 with rotations).
    pub values_per_node: usize,
    /// Record 7 after NINT and NRVAL: for a mode, the load case and the mode number.
    pub int_params: Vec<i64>,
    /// Record 8: for a normal mode frequency (Hz), modal mass, viscous and hysteretic damping
    /// ratios; for a complex mode the eigenvalue's real and imaginary parts (rad/s) and the
    /// modal A and B.
    pub real_params: Vec<f64>,
    /// Records 9–10, one per node, in file order.
    pub nodes: Vec<NodeValues>,
    /// 1-based line of the opening `-1`.
    pub line: usize,
}

/// The values of a dataset 55 at one node.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeValues {
    pub node: i64,
    /// NDV real parts (X, Y, Z[, RX, RY, RZ] for a vector).
    pub re: Vec<f64>,
    /// NDV imaginary parts, for complex data.
    pub im: Option<Vec<f64>>,
}

/// A mode's parameters from a dataset 55 ([`NodalData55::mode`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModeParams {
    /// Record 7's mode number, when given.
    pub mode_number: Option<i64>,
    /// Undamped natural frequency, Hz.
    pub freq_hz: f64,
    /// Viscous damping ratio.
    pub damping_ratio: f64,
    /// Modal mass, when the file gives one (0 is "not given").
    pub modal_mass: Option<f64>,
}

/// The bytes are not a UFF at all (nothing in them could be read as a dataset).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum UffError {
    #[error("empty input: expected a Universal File (a `-1` delimiter line), found 0 bytes")]
    Empty,
    #[error(
        "not a Universal File: expected a `-1` delimiter line followed by a dataset number, \
         found {first_line:?} on line 1 and no dataset"
    )]
    NotUff { first_line: String },
}
