//! The spec, row types, reader and writer of propagate's predictions.parquet.

use crate::io::tables::{self, Cols};
use crate::report::validation::Pred;
use arrow::array::Array;
use std::path::Path;

/// The rows of predictions.parquet.
pub fn read_preds(path: &Path) -> anyhow::Result<Vec<Pred>> {
    let mut out = vec![];
    for b in tables::read_parquet(path)? {
        let c = Cols { batch: &b, path };
        let (sc, bid, st, l, f, fo) = (
            c.str("scope")?,
            c.str("board_id")?,
            c.str("setup")?,
            c.str("label")?,
            c.f64("freq_hz")?,
            c.f64("freq_obs_hz")?,
        );
        // Absent from the predictions of a posterior without a discrepancy (older outputs).
        let disc = b
            .column_by_name("discrepancy_rel")
            .is_some()
            .then(|| c.f64("discrepancy_rel"))
            .transpose()?;
        for i in 0..b.num_rows() {
            out.push(Pred {
                scope: sc.value(i).into(),
                board_id: (!bid.is_null(i)).then(|| bid.value(i).to_string()),
                setup: st.value(i).into(),
                label: l.value(i).into(),
                freq_hz: f.value(i),
                freq_obs_hz: fo.value(i),
                discrepancy_rel: disc.map_or(0.0, |d| d.value(i)),
            });
        }
    }
    Ok(out)
}
