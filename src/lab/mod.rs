//! The virtual lab: simulates a complete measurement campaign (sheet, vibrometer UFF files,
//! balance logs) in the exact input format of `shared/campaign-format.md`, from a truth
//! model that is richer than the updating model, with switchable concealed physical
//! effects, and returns the truth separately.
//!
//! [`simulate`] is a pure function: scenario + board + seed → the campaign's files as bytes
//! (paths relative to the campaign directory) and the [`Truth`]. No file I/O; all
//! randomness flows from the seed through child seeds derived per purpose and per
//! board / measurement ([`child_seed`]), so the bytes do not depend on thread count or on
//! which effects are switched on (an effect scenario shares every draw with the null
//! scenario of the same seed).
//!
//! - [`scenario`]: the scenario files (`data/lab/*.toml`) and their validation;
//! - [`truth`]: the hierarchical truth (population draws, per-measurement contact
//!   stiffness and loose bolts, lab temperature) and the truth FE models and modes;
//! - [`effects`]: the concealed effects in plain words and their expected diagnosis;
//! - [`measure`]: the instruments: FRF synthesis by modal superposition, noise, coherence,
//!   drop-outs, the UFF files, the sheet and the balance logs;
//! - [`habits`]: the habits of a real lab in those files (check weights, spellings, a
//!   repeated measurement, scan grids, gaps), off unless the scenario asks for them.

pub mod effects;
pub mod habits;
pub mod measure;
pub mod scenario;
pub mod solid;
pub mod truth;

#[cfg(test)]
mod habit_tests;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod thickness_tests;

use std::collections::BTreeMap;

use rayon::prelude::*;

use crate::fem::{Board, FemError};

pub use scenario::Scenario;
pub use truth::Truth;

/// Built-in scenario files, by name (`paper` is the exact-model default campaign;
/// `realistic_*` are their counterparts on the solid truth with a real lab's habits).
pub const BUILTIN_SCENARIOS: [(&str, &str); 17] = [
    ("paper", include_str!("../../data/lab/paper.toml")),
    ("null", include_str!("../../data/lab/null.toml")),
    ("rotational", include_str!("../../data/lab/rotational.toml")),
    ("loose_bolt", include_str!("../../data/lab/loose_bolt.toml")),
    (
        "temperature",
        include_str!("../../data/lab/temperature.toml"),
    ),
    (
        "lumped_mass",
        include_str!("../../data/lab/lumped_mass.toml"),
    ),
    ("fixture", include_str!("../../data/lab/fixture.toml")),
    ("underfill", include_str!("../../data/lab/underfill.toml")),
    (
        "realistic_paper",
        include_str!("../../data/lab/realistic_paper.toml"),
    ),
    (
        "realistic_null",
        include_str!("../../data/lab/realistic_null.toml"),
    ),
    (
        "realistic_rotational",
        include_str!("../../data/lab/realistic_rotational.toml"),
    ),
    (
        "realistic_loose_bolt",
        include_str!("../../data/lab/realistic_loose_bolt.toml"),
    ),
    (
        "realistic_temperature",
        include_str!("../../data/lab/realistic_temperature.toml"),
    ),
    (
        "realistic_lumped_mass",
        include_str!("../../data/lab/realistic_lumped_mass.toml"),
    ),
    (
        "realistic_fixture",
        include_str!("../../data/lab/realistic_fixture.toml"),
    ),
    (
        "realistic_underfill",
        include_str!("../../data/lab/realistic_underfill.toml"),
    ),
    (
        "realistic_mass_and_temperature",
        include_str!("../../data/lab/realistic_mass_and_temperature.toml"),
    ),
];

/// Errors of the virtual lab.
#[derive(Debug, thiserror::Error)]
pub enum LabError {
    /// The scenario TOML could not be parsed (the message names the field).
    #[error("scenario: {0}")]
    ScenarioParse(String),
    /// A scenario value is out of range.
    #[error("scenario field `{field}`: expected {expected}, found {found}")]
    ScenarioInvalid {
        field: String,
        expected: String,
        found: String,
    },
    /// The physics core refused the truth model or its parameters.
    #[error("truth model: {0}")]
    Fem(#[from] FemError),
    /// A UFF record could not be written.
    #[error("writing {file}: {message}")]
    Write { file: String, message: String },
    /// The solid truth (its mesher, its solver or their outputs) failed.
    #[error("solid truth: {0}")]
    Solid(String),
    /// No built-in scenario of that name.
    #[error("built-in scenario: expected one of {expected:?}, found {found:?}")]
    UnknownBuiltin {
        expected: Vec<&'static str>,
        found: String,
    },
}

/// A simulated campaign: the files of the campaign directory and the truth behind them.
#[derive(Clone, Debug)]
pub struct SimulatedCampaign {
    /// Path relative to the campaign directory ('/'-separated) → file bytes.
    pub files: BTreeMap<String, Vec<u8>>,
    /// Everything that is not in the files (to be written to a separate truth file).
    pub truth: Truth,
}

/// Parse a built-in scenario by name.
pub fn builtin_scenario(name: &str) -> Result<Scenario, LabError> {
    let text = BUILTIN_SCENARIOS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, t)| *t)
        .ok_or_else(|| LabError::UnknownBuiltin {
            expected: BUILTIN_SCENARIOS.iter().map(|(n, _)| *n).collect(),
            found: name.to_string(),
        })?;
    Scenario::from_toml_str(text)
}

/// Purposes of the child random streams.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Stream {
    Board = 1,
    Bolted = 2,
    Temperature = 3,
    Measurement = 4,
    Balance = 5,
    /// The lab habits' draws (a stream of their own: switching them leaves the others alone).
    Habits = 6,
    /// Each board's core thickness (its own stream: the moduli and mass draws stay as before).
    Thickness = 7,
}

/// Child seed for `stream` and `index`: SplitMix64 finalisers over (seed, stream, index),
/// so every board and measurement has its own independent stream whatever the order or
/// thread count in which they are simulated.
pub(crate) fn child_seed(seed: u64, stream: Stream, index: u64) -> u64 {
    fn mix(mut z: u64) -> u64 {
        z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    mix(mix(mix(seed) ^ (stream as u64)) ^ index)
}

/// Simulate the campaign of `scenario` for `board` with `seed`.
///
/// Deterministic: equal inputs give equal bytes and an equal truth, whatever the number
/// of rayon threads.
pub fn simulate(
    scenario: &Scenario,
    board: &Board,
    seed: u64,
) -> Result<SimulatedCampaign, LabError> {
    simulate_with(scenario, board, seed, None)
}

/// [`simulate`] with the external programs a solid truth (`[truth] physics = "solid"`)
/// needs; a scenario on the solid truth without them is an error.
pub fn simulate_with(
    scenario: &Scenario,
    board: &Board,
    seed: u64,
    solver: Option<std::sync::Arc<dyn solid::Solver>>,
) -> Result<SimulatedCampaign, LabError> {
    scenario.validate()?;
    board.validate()?;
    let mut plan = truth::plan(scenario, board, seed)?;
    let habits = habits::apply(scenario, board, &mut plan)?;
    let models = truth::Models::build(scenario, board, solver)?;
    let free_cache = truth::free_board_modes(scenario, &plan, &models)?;
    let results: Vec<(truth::MeasurementTruth, Vec<u8>)> = plan
        .measurements
        .par_iter()
        .map(|m| {
            let ms = truth::measurement_modes(scenario, &plan, &models, &free_cache, m)?;
            let points: Vec<[f64; 3]> = match &m.habits.grid {
                Some(g) => g.all_points(),
                None => models.points.iter().map(|p| [p[0], p[1], 0.0]).collect(),
            };
            let bytes = measure::measurement_uff(scenario, &points, m, &ms, seed)?;
            Ok((ms.truth, bytes))
        })
        .collect::<Result<_, LabError>>()?;
    let mut files = BTreeMap::new();
    let mut meas_truth = Vec::with_capacity(results.len());
    for (m, (t, bytes)) in plan.measurements.iter().zip(results) {
        files.insert(m.file.clone(), bytes);
        meas_truth.push(t);
    }
    files.insert(
        "campaign.csv".to_string(),
        measure::sheet_csv(
            &plan.measurements,
            scenario
                .campaign
                .sheet_dimensions
                .then_some((board, plan.boards.as_slice())),
        )?,
    );
    let misfit = truth::model_misfit(scenario, board, &models)?;
    let mut truth = truth::assemble(scenario, board, &plan, &free_cache, meas_truth, misfit);
    let logs = measure::balance_logs(scenario, &plan, &truth.boards);
    for (name, bytes) in logs.files {
        files.insert(name, bytes);
    }
    truth.garbled_balance_lines = logs.garbled;
    if scenario.habits().any() {
        let mut h = habits;
        h.balance_id_variants = logs.id_variants;
        h.reweighed = logs.reweighed;
        truth.habits = Some(h);
    }
    Ok(SimulatedCampaign { files, truth })
}
