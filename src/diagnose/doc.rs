//! `diagnosis.json` ([`DiagnosisDoc`]) and the options of `hbmu diagnose` it records.

use crate::diagnose::library::Mechanism;
use crate::diagnose::locate::{LocateOptions, Located};
use crate::diagnose::regions;
use crate::diagnose::screen::Candidate;
use crate::diagnose::select::{Compared, Estimate, SelectOptions, Verdict};
use crate::findings::Finding;
use std::path::PathBuf;

/// One favoured finding of `diagnosis.json`.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct FindingDoc {
    /// Mechanism id.
    pub mechanism: Mechanism,
    /// Where the finding is: the joint and its centre (per-joint mechanisms) or the located
    /// point (`added_mass`); null for mechanisms without a place.
    pub location: Option<Location>,
    /// The sheet column the finding follows, if any.
    pub covariate: Option<String>,
    /// Parameter estimates: population median with its 90 % interval.
    pub estimates: Vec<Estimate>,
    pub log_bayes_factor: Option<f64>,
    pub log_bayes_factor_se: Option<f64>,
    /// Held-out mean absolute frequency error before and after, per setup, percent.
    pub held_out_error: Vec<HeldOut>,
    /// The same over the outlier measurements the locate step singled out, where the
    /// mechanism acts on some assemblies only (absent without outliers).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub held_out_error_outliers: Vec<HeldOut>,
    /// The refit's directory, relative to the diagnosis directory.
    pub refit_dir: String,
    pub sentence: String,
}

#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct Location {
    /// 1-based, hole order of the board file; absent for a point on the board.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub joint: Option<usize>,
    pub x_m: f64,
    pub y_m: f64,
}

#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct HeldOut {
    pub setup: String,
    pub before_percent: f64,
    pub after_percent: f64,
}

/// One screened candidate of `diagnosis.json`, with its refit when it had one.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct CandidateDoc {
    pub id: String,
    pub candidate: Candidate,
    pub refit: Option<Compared>,
    pub sentence: String,
}

/// `diagnosis.json`.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct DiagnosisDoc {
    pub verdict: Verdict,
    /// What locate found (the summary; `checks` has the tests behind it).
    pub located: LocatedSummary,
    /// Favoured mechanisms, strongest first.
    pub findings: Vec<FindingDoc>,
    /// Every screened candidate, refitted ones first in order of their Bayes factor.
    pub candidates: Vec<CandidateDoc>,
    pub remaining_discrepancy: String,
    pub options: DiagnoseOptions,
    pub checks: Located,
    /// Problems met on the way (missing tables, quarantined measurements, the verdict).
    pub stage_findings: Vec<Finding>,
}

/// The located evidence in short.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct LocatedSummary {
    /// Anything located by the statistical tests (at the tolerance of `options.locate`).
    pub any: bool,
    /// A structured misfit at or above the practical threshold (`options.select`): a located
    /// mode's mean shift or covariate trend that large, an outlier measurement or a recurring
    /// unpaired mode. Only then are candidates refitted and a misfit reported.
    pub above_practical_threshold: bool,
    /// The largest |mean relative residual| of any checked mode (`setup label`) and its
    /// value: how far the model is from these boards at worst.
    pub largest_mode_misfit: Option<(String, f64)>,
    pub setups: Vec<String>,
    pub modes: Vec<crate::diagnose::locate::LocatedMode>,
    pub measurements: Vec<String>,
    /// Outliers of `measurements` by their mode shapes (every mode's MAC against the model
    /// lower than the setup's other measurements'), with the check of each
    /// ([`crate::diagnose::shapes`]).
    pub shape_outliers: Vec<crate::diagnose::shapes::ShapeCheck>,
    /// Outlier measurements whose deviation is one mode's alone (likely identification
    /// slips; not counted as misfit).
    pub identification_outliers: Vec<crate::diagnose::locate::IdentificationOutlier>,
    pub covariates: Vec<crate::diagnose::locate::LocatedCovariate>,
    pub unpaired_clusters: Vec<crate::diagnose::locate::UnpairedCluster>,
    pub never_seen: Vec<crate::diagnose::locate::ModelModePresence>,
    /// Board regions: the point-mass localisation of the free-free misfit
    /// ([`regions::point_mass_region`]); empty when it did not run, `board_regions_note`
    /// says why, and what is not localised yet.
    pub board_regions: Vec<regions::BoardRegion>,
    pub board_regions_note: String,
}

/// Options of `hbmu diagnose`.
#[derive(Debug, Clone, serde::Serialize, schemars::JsonSchema)]
pub struct DiagnoseOptions {
    #[serde(skip)]
    pub work_dir: PathBuf,
    #[serde(skip)]
    pub out: PathBuf,
    #[serde(skip)]
    pub board: Option<PathBuf>,
    #[serde(skip)]
    pub force: bool,
    /// Run only this candidate's refit (its id, e.g. `joint_rotation` or
    /// `joint_stiffness_per_joint_2`) and stop: the cluster fan-out.
    #[serde(skip)]
    pub only: Option<String>,
    pub locate: LocateOptions,
    pub select: SelectOptions,
    /// Refit at most this many screened candidates per part of the located misfit
    /// (`misfit::Part`; 0: locate and screen only).
    pub max_refits: usize,
}
