//! `extract/modes.parquet` read back: one [`ModeRow`] per (measurement, mode), in file order,
//! with the identification band and the scan points and shape as lists. The stages that use
//! identified modes (`pair`, `update`, `diagnose`) take what they need from these rows; a
//! missing column or one of the wrong type is an error naming the file and column.

use crate::io::tables::{self, Cols};
use std::path::Path;

pub use crate::modal::rows::ModeRow;

/// Every row of `modes.parquet` at `path`, in file order.
pub fn read_modes_table(path: &Path) -> anyhow::Result<Vec<ModeRow>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (id, board, setup, mode, f, zeta, lo, hi) = (
            c.str("measurement_id")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.i32("mode")?,
            c.f64("freq_hz")?,
            c.f64("damping_ratio")?,
            c.f64("band_lo_hz")?,
            c.f64("band_hi_hz")?,
        );
        for i in 0..b.num_rows() {
            out.push(ModeRow {
                measurement_id: id.value(i).to_string(),
                board_id: board.value(i).to_string(),
                setup: setup.value(i).to_string(),
                mode: mode.value(i),
                freq_hz: f.value(i),
                damping_ratio: zeta.value(i),
                band_lo_hz: lo.value(i),
                band_hi_hz: hi.value(i),
                node: c.list_i64("node", i)?,
                x_m: c.list_f64("x_m", i)?.unwrap_or_default(),
                y_m: c.list_f64("y_m", i)?.unwrap_or_default(),
                shape: c.list_f64("shape", i)?.unwrap_or_default(),
            });
        }
    }
    Ok(out)
}
