//! The joint family: symmetry, definiteness, reduction to the baseline as a variant's
//! parameter vanishes, monotonicity (Rayleigh), the general-mass ROM path, and the
//! lumped point mass.

use crate::fem::board::Board;
use crate::fem::joints::{JointFeature, JointModel};
use crate::fem::model::{FeModel, Setup};
use crate::fem::params::names;
use crate::fem::rom::{latin_hypercube_params, Rom, RomOptions};

fn board() -> Board {
    Board::default_board()
}

fn model(features: Vec<JointFeature>) -> FeModel {
    let b = board();
    FeModel::build(&b, Setup::Bolted(JointModel { features }), &b.mesh).unwrap()
}

fn freqs(m: &FeModel, n: usize) -> Vec<f64> {
    m.modes(&m.nominal_params(), n).unwrap().freq_hz
}

fn close(a: &[f64], b: &[f64], tol: f64) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol * y.abs())
}

fn variants() -> Vec<Vec<JointFeature>> {
    vec![
        vec![JointFeature::Translational],
        vec![JointFeature::PerJointTranslational],
        vec![
            JointFeature::Translational,
            JointFeature::RotationalRestraint {
                k_rot_nm_per_rad: 5.0,
            },
        ],
        vec![
            JointFeature::Translational,
            JointFeature::JointMass { mass_kg: 1.2e-3 },
        ],
        vec![
            JointFeature::Translational,
            JointFeature::CompliantFixture {
                k_fix_n_per_m: 1e8,
                m_fix_kg: 0.2,
            },
        ],
    ]
}

#[test]
fn every_variant_is_symmetric_and_positive_definite() {
    for f in variants() {
        let m = model(f.clone());
        let p = m.nominal_params();
        for trip in [
            m.stiffness_triplets(&p).unwrap(),
            m.mass_triplets(&p).unwrap(),
        ] {
            let mut map = std::collections::HashMap::new();
            for (r, c, v) in &trip {
                map.insert((*r, *c), *v);
            }
            for ((r, c), v) in &map {
                let t = map.get(&(*c, *r)).copied().unwrap_or(0.0);
                assert!(
                    (v - t).abs() <= 1e-12 * v.abs().max(t.abs()).max(1e-300),
                    "{f:?}: asymmetric at ({r}, {c})"
                );
            }
        }
        // Fixed-base: K and M positive definite, so every eigenvalue is positive.
        let modes = m.modes(&p, 7).unwrap();
        assert!(
            modes.eigenvalues[0] > 0.0,
            "{f:?}: lowest eigenvalue {}",
            modes.eigenvalues[0]
        );
        assert_eq!(modes.n_rigid_dropped, 0);
    }
}

#[test]
fn variants_reduce_to_the_baseline() {
    let base = freqs(&model(vec![JointFeature::Translational]), 7);
    // Equal per-joint stiffnesses = one K_con.
    assert!(close(
        &freqs(&model(vec![JointFeature::PerJointTranslational]), 7),
        &base,
        1e-9
    ));
    // Zero rotational restraint, zero joint mass.
    let zero_rot = model(vec![
        JointFeature::Translational,
        JointFeature::RotationalRestraint {
            k_rot_nm_per_rad: 0.0,
        },
    ]);
    assert!(close(&freqs(&zero_rot, 7), &base, 1e-9));
    let zero_mass = model(vec![
        JointFeature::Translational,
        JointFeature::JointMass { mass_kg: 0.0 },
    ]);
    assert!(close(&freqs(&zero_mass, 7), &base, 1e-9));
    // A fixture that becomes rigid (compliance → 0): the modes tend to the baseline.
    let mut last = f64::INFINITY;
    for k_fix in [1e9, 1e11, 1e13] {
        let m = model(vec![
            JointFeature::Translational,
            JointFeature::CompliantFixture {
                k_fix_n_per_m: k_fix,
                m_fix_kg: 0.05,
            },
        ]);
        let f = freqs(&m, 7);
        let err = f
            .iter()
            .zip(&base)
            .map(|(a, b)| (a - b).abs() / b)
            .fold(0.0, f64::max);
        assert!(
            err < last,
            "fixture k = {k_fix}: error {err} did not shrink"
        );
        last = err;
    }
    assert!(last < 1e-5, "stiff fixture: error {last}");
}

#[test]
fn added_stiffness_raises_and_added_mass_lowers_every_frequency() {
    let base = freqs(&model(vec![JointFeature::Translational]), 7);
    let rot = freqs(
        &model(vec![
            JointFeature::Translational,
            JointFeature::RotationalRestraint {
                k_rot_nm_per_rad: 5.0,
            },
        ]),
        7,
    );
    let mass = freqs(
        &model(vec![
            JointFeature::Translational,
            JointFeature::JointMass { mass_kg: 1.2e-3 },
        ]),
        7,
    );
    for j in 0..7 {
        assert!(
            rot[j] >= base[j] * (1.0 - 1e-12),
            "mode {j}: {} < {}",
            rot[j],
            base[j]
        );
        assert!(
            mass[j] <= base[j] * (1.0 + 1e-12),
            "mode {j}: {} > {}",
            mass[j],
            base[j]
        );
    }
    // Per-joint: stiffening one joint raises (or keeps) every frequency.
    let m = model(vec![JointFeature::PerJointTranslational]);
    let mut p = m.nominal_params();
    let k1 = names::k_con_joint(1);
    p.set(&k1, 3.0 * p.get(&k1).unwrap()).unwrap();
    let stiff = m.modes(&p, 7).unwrap().freq_hz;
    for j in 0..7 {
        assert!(stiff[j] >= base[j] * (1.0 - 1e-12));
    }
}

#[test]
fn rom_with_two_mass_terms_matches_the_full_model() {
    let m = model(vec![
        JointFeature::Translational,
        JointFeature::JointMass { mass_kg: 1.2e-3 },
    ]);
    assert_eq!(m.map.m_coefs.len(), 2);
    let rom = Rom::build(
        &m,
        &RomOptions {
            n_modes: 7,
            ..RomOptions::default()
        },
    )
    .unwrap();
    let pts = m.board.scan_points_m();
    let sop = rom.shape_operator(&m, &pts).unwrap();
    for p in latin_hypercube_params(&m.map, 12, 0.2, 99) {
        let full = m.modes(&p, 7).unwrap();
        let red = rom.eval(&p, &sop).unwrap();
        for j in 0..7 {
            let e = (red.freq_hz[j] - full.freq_hz[j]).abs() / full.freq_hz[j];
            assert!(
                e < 1e-3,
                "mode {j}: ROM {} vs full {}",
                red.freq_hz[j],
                full.freq_hz[j]
            );
        }
    }
}

#[test]
fn point_mass_adds_exactly_its_mass_and_lowers_frequencies() {
    let b = board();
    let mut m = FeModel::build(&b, Setup::Free, &b.mesh).unwrap();
    let p = m.nominal_params();
    let m0 = m.total_mass_kg(&p).unwrap();
    let f0 = m.modes(&p, 8).unwrap().freq_hz;
    m.add_point_mass(0.0313, 0.0171, 2e-3).unwrap();
    // Partition of unity of the w shape functions: rᵀ (m N Nᵀ) r = m.
    assert!((m.total_mass_kg(&p).unwrap() - m0 - 2e-3).abs() < 1e-15);
    let f1 = m.modes(&p, 8).unwrap().freq_hz;
    assert!(f1.iter().zip(&f0).all(|(a, b)| *a <= *b * (1.0 + 1e-12)));
    assert!(
        m.add_point_mass(0.1, 0.01, 1e-3).is_err(),
        "outside the board"
    );
    assert!(
        m.add_point_mass(0.005, 0.005, 1e-3).is_err(),
        "inside a hole"
    );
}

#[test]
fn effective_masses_sum_to_at_most_the_total_mass() {
    // Σ Γᵢ² over all modes equals rᵀ M r; over the lowest 20 it is at most that.
    let m = model(vec![JointFeature::Translational]);
    let p = m.nominal_params();
    let modes = m.modes(&p, 20).unwrap();
    let gam = m.participation_z(&p, &modes).unwrap();
    let eff: f64 = gam.iter().map(|g| g * g).sum();
    let total = m.total_mass_kg(&p).unwrap();
    assert!(
        eff <= total * (1.0 + 1e-9) && eff > 0.5 * total,
        "effective {eff}, total {total}"
    );
}
