//! The default board: parses, weighs about 13 g, frequencies near the paper's.

use crate::fem::board::Board;
use crate::fem::model::{FeModel, Setup};

#[test]
fn default_board_mass_and_frequencies_resemble_the_paper() {
    let b = Board::default_board();
    let m = FeModel::build(&b, Setup::Free, &b.mesh).unwrap();
    let p = m.nominal_params();
    let mass = m.total_mass_kg(&p).unwrap();
    let modes = m.modes(&p, 8).unwrap();
    eprintln!("mass {mass} kg, ndof {}, dropped {}, f {:?}", m.n_dof, modes.n_rigid_dropped, modes.freq_hz);
    let mb = FeModel::build(&b, Setup::bolted(), &b.mesh).unwrap();
    let mo = mb.modes(&mb.nominal_params(), 8).unwrap();
    eprintln!("bolted f {:?}", mo.freq_hz);
    assert!((mass - 0.013).abs() < 0.0005, "mass {mass} kg, expected about 13 g");
    assert_eq!(modes.n_rigid_dropped, 3);
}
