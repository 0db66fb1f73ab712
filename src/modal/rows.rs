//! Rows of the measurement side's tables as the later stages use them: an identified mode
//! with its shape ([`ModeRow`], extract's modes.parquet) and an accepted pair of an identified
//! and a model mode ([`PairRow`], pair's pairs.parquet). Plain data: io reads them, the
//! kernels take them.

/// One row of `modes.parquet` (the columns the later stages use).
#[derive(Clone, Debug, PartialEq)]
pub struct ModeRow {
    pub measurement_id: String,
    pub board_id: String,
    /// `free` or `bolted`.
    pub setup: String,
    /// Identified mode number in the measurement, 1-based.
    pub mode: i32,
    pub freq_hz: f64,
    /// Viscous damping ratio (dimensionless).
    pub damping_ratio: f64,
    pub band_lo_hz: f64,
    pub band_hi_hz: f64,
    /// Scan-point node labels.
    pub node: Vec<i64>,
    /// Scan-point coordinates (m), aligned with `node`.
    pub x_m: Vec<f64>,
    pub y_m: Vec<f64>,
    /// Real-normalised shape at the scan points (NaN where a point was excluded; empty when
    /// null).
    pub shape: Vec<f64>,
}

/// An accepted pair of pairs.parquet: an identified mode with a frequency and the model mode it
/// pairs with.
#[derive(Debug, Clone)]
pub struct PairRow {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub mode: i32,
    pub freq_hz: f64,
    pub model_mode: i32,
    pub label: String,
}
