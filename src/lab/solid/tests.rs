//! Unit tests of the solid truth's pure parts (no external program): the mesh reader, the
//! extrusion, the interpolation, the deck and the output reader.

use super::ccx::{self, Loading, Material};
use super::mesh::{self, Layer};

/// Two unit... a 2 × 1 mm strip of two 8-node quads, the second written clockwise.
const TWO_QUADS: &str = "*Heading\n*NODE\n1, 0, 0, 0\n2, 1, 0, 0\n3, 2, 0, 0\n4, 0, 1, 0\n5, 1, 1, 0\n6, 2, 1, 0\n\
7, 0.5, 0, 0\n8, 1.5, 0, 0\n9, 0.5, 1, 0\n10, 1.5, 1, 0\n11, 0, 0.5, 0\n12, 1, 0.5, 0\n13, 2, 0.5, 0\n\
******* E L E M E N T S *************\n*ELEMENT, type=T3D3, ELSET=Line1\n1, 1, 2, 7\n\
*ELEMENT, type=CPS8, ELSET=Surface1\n2, 1, 2, 5, 4, 7, 12, 9, 11\n3, 2, 5, 6, 3, 12, 10, 13, 8\n";

#[test]
fn gmsh_mesh_is_read_and_oriented_counter_clockwise() {
    let m = mesh::parse_gmsh_inp(TWO_QUADS).unwrap();
    assert_eq!(m.quads.len(), 2);
    for e in 0..2 {
        assert!((m.area(e) - 1.0).abs() < 1e-12, "area {}", m.area(e));
        let w = m.face_weights(e);
        assert!(w.iter().all(|v| *v > 0.0), "HRZ weights positive: {w:?}");
    }
    // A field linear in x and y is interpolated exactly, anywhere.
    let f: Vec<f64> = m
        .xy_mm
        .iter()
        .map(|p| 3.0 * p[0] - 2.0 * p[1] + 1.0)
        .collect();
    for p in [[0.3, 0.7], [1.9, 0.1], [1.0, 0.5]] {
        let (e, xi) = m.locate(p).unwrap();
        let v = m.interpolate(&f, e, xi);
        assert!((v - (3.0 * p[0] - 2.0 * p[1] + 1.0)).abs() < 1e-12);
    }
    assert!(m.locate([2.5, 0.5]).is_none(), "off the mesh");
}

#[test]
fn bad_mesh_lines_name_the_line() {
    let text = TWO_QUADS.replace(
        "3, 2, 5, 6, 3, 12, 10, 13, 8",
        "3, 2, 5, 6, 3, 12, 10, 13, 99",
    );
    let e = mesh::parse_gmsh_inp(&text).unwrap_err();
    assert!(e.contains("node 99 is not defined"), "{e}");
    let text = TWO_QUADS.replace("type=CPS8", "type=CPS6");
    let e = mesh::parse_gmsh_inp(&text).unwrap_err();
    assert!(
        e.contains("8-node quadrilaterals") && e.contains("CPS6"),
        "{e}"
    );
}

#[test]
fn extrusion_puts_copper_bricks_only_where_copper_lies() {
    let m = mesh::parse_gmsh_inp(TWO_QUADS).unwrap();
    let layers = [
        Layer {
            z0_mm: -0.5,
            z1_mm: 0.5,
            class: vec![Some(0), Some(0)],
        },
        Layer {
            z0_mm: 0.5,
            z1_mm: 0.52,
            class: vec![Some(1), None],
        },
    ];
    let m3 = mesh::extrude(&m, &layers);
    assert_eq!(m3.bricks.len(), 3);
    // Core: 13 nodes at the bottom and at the top, 6 corners at mid-height; copper over the
    // first element: 8 nodes at its top, 4 corners at its mid-height.
    assert_eq!(m3.xyz_mm.len(), 13 + 13 + 6 + 8 + 4);
    // The top face over element 1 is the copper's, over element 2 the core's.
    let z_top = |n: usize| m3.xyz_mm[m3.top[n].unwrap()][2];
    assert_eq!(z_top(0), 0.52); // node 1, first element only
    assert_eq!(z_top(2), 0.5); // node 3, second element only
    assert_eq!(z_top(1), 0.52); // node 2, shared: the higher face
    assert!(m3.bottom.iter().all(|b| m3.xyz_mm[b.unwrap()][2] == -0.5));
    // Every brick's corners 0–3 lie below 4–7 with the same (x, y).
    for (_, _, b) in &m3.bricks {
        for k in 0..4 {
            let (p, q) = (m3.xyz_mm[b[k]], m3.xyz_mm[b[4 + k]]);
            assert!(p[0] == q[0] && p[1] == q[1] && p[2] < q[2]);
        }
    }
    let load = Loading {
        materials: vec![Material::isotropic(1e3, 0.3, 1e-9); 2],
        n_modes: 3,
        ..Loading::default()
    };
    let deck = ccx::deck(&m3, &load);
    assert!(deck.contains("*ELEMENT, TYPE=C3D20, ELSET=C0"));
    assert!(deck.contains("*ELEMENT, TYPE=C3D20, ELSET=C1"));
    assert!(deck.contains("*FREQUENCY\n3\n"));
    // No data line longer than CalculiX's 132 characters.
    assert!(deck.lines().all(|l| l.len() <= 132));

    // A compliant fixture: its node follows the mesh's, the joint springs marked for it are
    // two-node springs to it, and it moves in z only on its own spring with its mass.
    let n = m3.xyz_mm.len();
    let load = Loading {
        materials: vec![Material::isotropic(1e3, 0.3, 1e-9); 2],
        springs: vec![
            ccx::Spring {
                node: 0,
                dof: 3,
                k_n_per_mm: 5.0,
                to_fixture: true,
            },
            ccx::Spring {
                node: 0,
                dof: 1,
                k_n_per_mm: 4.0,
                to_fixture: false,
            },
        ],
        fixture: Some(ccx::Fixture {
            at_mm: [-12.0, 25.0, -8.0],
            k_n_per_mm: 3e4,
            mass_t: 1e-4,
        }),
        n_modes: 3,
        ..Loading::default()
    };
    let deck = ccx::deck(&m3, &load);
    let f = n + 1;
    assert!(deck.contains(&format!(
        "\n{f}, -1.2000000000e1, 2.5000000000e1, -8.0000000000e0\n"
    )));
    assert!(deck.contains(&format!(
        "*ELEMENT, TYPE=SPRING2, ELSET=S0\n{}, 1, {f}\n*SPRING, ELSET=S0\n3,3\n",
        3 + 1
    )));
    assert!(deck.contains("*ELEMENT, TYPE=SPRING1, ELSET=S1\n"));
    assert!(deck.contains("*SPRING, ELSET=SFIX\n3\n3.0000000000e4"));
    assert!(deck.contains("*MASS, ELSET=MFIX\n1.0000000000e-4"));
    assert!(deck.contains(&format!("*BOUNDARY\n{f}, 1, 2\n")));
}

/// The reader against an excerpt of a real CalculiX 2.20 `.dat` (two modes, two nodes).
#[test]
fn dat_output_is_read() {
    let dat = "
     E I G E N V A L U E   O U T P U T

 MODE NO    EIGENVALUE                       FREQUENCY   
                                     REAL PART            IMAGINARY PART
                           (RAD/TIME)      (CYCLES/TIME     (RAD/TIME)

      1  -0.3819893E-03   0.0000000E+00   0.0000000E+00   0.1954455E-01
      2   0.2069719E+08   0.4549417E+04   0.7240622E+03   0.0000000E+00

     P A R T I C I P A T I O N   F A C T O R S

MODE NO.   X-COMPONENT     Y-COMPONENT     Z-COMPONENT     X-ROTATION      Y-ROTATION      Z-ROTATION

      1  -0.1408889E-03  -0.2083371E-03  -0.2288930E-03  -0.6391836E-02   0.1126301E-01   0.9164971E-01
      2   0.3802604E-07   0.7715247E-08   0.3106004E-13   0.1652120E-07  -0.7716102E-08  -0.1542867E-12

                    E I G E N V A L U E    N U M B E R     1


 displacements (vx,vy,vz) for set NTOP and time  0.1954455E-01

         5  1.0E-01  2.0E-01  3.0E-01
         7  4.0E-01  5.0E-01 -6.0E-01

 total mass for set EALL and time  0.1000000E+01

        1.265569E-05

 total mass moment of inertia (xx,yy,zz,xy,xz,yz) for set EALL and time  0.1000000E+01

        2.697638E-02  1.053772E-02  2.623850E-06  1.264524E-02 -1.958584E-05 -1.224115E-05

 center of gravity for set EALL and time  0.1000000E+01

        3.997E+01  2.498E+01  0.0E+00

 total mass moment of inertia about the center ofgravity (xx,yy,zz,xy,xz,yz) for set EALL and time  0.1000000E+01

        6.758244E-03  2.639349E-03  2.604906E-06  8.368227E-06 -1.498195E-08 -8.848252E-09

                    E I G E N V A L U E    N U M B E R     2


 displacements (vx,vy,vz) for set NTOP and time  0.7240622E+03

         5  1.0E-01  2.0E-01  7.0E-01
         7  4.0E-01  5.0E-01  8.0E-01

 total mass for set EALL and time  0.1000000E+01

        9.9E-05
";
    let r = ccx::parse_dat(dat).unwrap();
    assert_eq!(r.freq_hz, vec![0.0, 724.0622]);
    assert_eq!(r.participation[0][2], -0.2288930E-03);
    assert_eq!(
        r.uz,
        vec![vec![(4, 0.3), (6, -0.6)], vec![(4, 0.7), (6, 0.8)]]
    );
    assert_eq!(r.mass_t, 1.265569E-05, "the first mass block");
    assert_eq!(
        r.second_moments_cog,
        [6.758244E-03, 2.639349E-03, 8.368227E-06]
    );
    assert_eq!(r.cog_mm, [39.97, 24.98, 0.0]);
    let e = ccx::parse_dat(&dat.replace("P A R T I C I P A T I O N", "nothing")).unwrap_err();
    assert!(e.contains("participation factors"), "{e}");
}
