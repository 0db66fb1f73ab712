//! The step-1 posterior as step 2 carries it: every board's parameter draws, and a point mass a
//! board mechanism's step-1 refit added.

use anyhow::bail;

/// Step-1 posterior draws read back from boards.parquet.
pub struct Step1 {
    /// Boards in the order of `values` blocks.
    pub board_ids: Vec<String>,
    /// The updated parameters (ROM names), in column order.
    pub params: Vec<String>,
    /// Coefficients of a board enrichment (e.g. `temperature_coefficient_per_k`), after the
    /// parameters in every board's block.
    pub coefs: Vec<String>,
    /// Per (run, draw): every board's parameter and coefficient values, board-major.
    pub draws: Vec<((i32, i32), Vec<f64>)>,
}

impl Step1 {
    /// Values per board in a draw: parameters, then coefficients.
    pub fn block(&self) -> usize {
        self.params.len() + self.coefs.len()
    }
}

/// A point mass a step-1 refit added to the boards: its parameter, point and posterior mean.
pub struct Step1PointMass {
    pub parameter: String,
    pub x_m: f64,
    pub y_m: f64,
    /// Mean over every board and draw, kg (the bolted ROM's centre along it).
    pub mean_kg: f64,
}

/// The point mass of a step-1 enrichment (its `effect` of kind `point_mass`), if any.
pub fn step1_point_mass(
    enrichment: &serde_json::Value,
    step1: &Step1,
    step1_source: &str,
) -> anyhow::Result<Option<Step1PointMass>> {
    let e = &enrichment["effect"];
    if e["kind"].as_str() != Some("point_mass") {
        return Ok(None);
    }
    let parameter = e["parameter"].as_str().unwrap_or_default().to_string();
    let (Some(x_m), Some(y_m)) = (e["x_m"].as_f64(), e["y_m"].as_f64()) else {
        bail!(
            "{}: the step-1 enrichment's point mass has no x_m/y_m",
            step1_source
        );
    };
    let Some(k) = step1.params.iter().position(|p| *p == parameter) else {
        bail!(
            "{}: no column {parameter:?}, the step-1 enrichment's added mass",
            step1_source
        );
    };
    let d1 = step1.block();
    let nb = step1.board_ids.len();
    let (mut sum, mut n) = (0.0, 0usize);
    for (_, v) in &step1.draws {
        for b in 0..nb {
            sum += v[b * d1 + k];
            n += 1;
        }
    }
    Ok(Some(Step1PointMass {
        parameter,
        x_m,
        y_m,
        mean_kg: sum / n.max(1) as f64,
    }))
}
