//! CalculiX's input deck for a frequency step on the extruded mesh, and the parts of its
//! `.dat` output the truth reads (eigenvalues, participation factors, top-face
//! displacements per mode, the bricks' mass and its moments).
//!
//! Units of the deck: mm, N, t (tonne), MPa, so t/mm³ for densities and N/mm for springs.

use std::fmt::Write;

use super::mesh::Mesh3;

/// An orthotropic material in the board frame (x, y in-plane, z through the thickness).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    /// E_x, E_y, E_z, MPa.
    pub e_mpa: [f64; 3],
    /// ν_xy, ν_xz, ν_yz.
    pub nu: [f64; 3],
    /// G_xy, G_xz, G_yz, MPa.
    pub g_mpa: [f64; 3],
    /// Density, t/mm³.
    pub rho_t_per_mm3: f64,
}

impl Material {
    /// An isotropic material from E (MPa), ν and density (t/mm³).
    pub fn isotropic(e_mpa: f64, nu: f64, rho_t_per_mm3: f64) -> Material {
        let g = e_mpa / (2.0 * (1.0 + nu));
        Material {
            e_mpa: [e_mpa; 3],
            nu: [nu; 3],
            g_mpa: [g; 3],
            rho_t_per_mm3,
        }
    }
}

/// A spring on one node's translation `dof` (1 | 2 | 3 for x | y | z), N/mm, to the ground or,
/// when `to_fixture`, to the fixture's node in the same direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Spring {
    pub node: usize,
    pub dof: u8,
    pub k_n_per_mm: f64,
    pub to_fixture: bool,
}

/// A compliant fixture: one node at `at_mm` moving in z only, of mass `mass_t`, on a spring
/// `k_n_per_mm` to the shaker's armature (the ground of the relative motion).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fixture {
    pub at_mm: [f64; 3],
    pub k_n_per_mm: f64,
    pub mass_t: f64,
}

/// A point mass on one node, t.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointMass {
    pub node: usize,
    pub mass_t: f64,
}

/// Everything a frequency step needs beyond the mesh.
#[derive(Clone, Debug, Default)]
pub struct Loading {
    /// Material of each brick class (index = class).
    pub materials: Vec<Material>,
    pub springs: Vec<Spring>,
    pub masses: Vec<PointMass>,
    /// Held degrees of freedom: (node, 1 | 2 | 3 for x | y | z).
    pub fixed: Vec<(usize, u8)>,
    /// The compliant fixture the springs marked `to_fixture` attach to.
    pub fixture: Option<Fixture>,
    /// Eigenmodes to compute.
    pub n_modes: usize,
}

fn num(v: f64) -> String {
    format!("{v:.10e}")
}

/// The CalculiX input deck. Node and element numbers are 1-based in the deck; the top-face
/// node set `NTOP` is the set whose displacements are printed.
pub fn deck(mesh: &Mesh3, load: &Loading) -> String {
    let mut s = String::with_capacity(64 * mesh.xyz_mm.len() + 160 * mesh.bricks.len());
    s.push_str("*HEADING\nhbmu virtual lab: solid truth\n*NODE, NSET=NALL\n");
    for (i, p) in mesh.xyz_mm.iter().enumerate() {
        let _ = writeln!(s, "{}, {}, {}, {}", i + 1, num(p[0]), num(p[1]), num(p[2]));
    }
    // The fixture's node follows the mesh's.
    let fixture_node = mesh.xyz_mm.len() + 1;
    if let Some(f) = &load.fixture {
        let _ = writeln!(
            s,
            "{fixture_node}, {}, {}, {}",
            num(f.at_mm[0]),
            num(f.at_mm[1]),
            num(f.at_mm[2])
        );
    }
    let n_classes = load.materials.len();
    let mut eid = 1usize;
    for c in 0..n_classes {
        let members: Vec<&[usize; 20]> = mesh
            .bricks
            .iter()
            .filter(|(cl, _, _)| *cl == c)
            .map(|(_, _, b)| b)
            .collect();
        if members.is_empty() {
            continue;
        }
        let _ = writeln!(s, "*ELEMENT, TYPE=C3D20, ELSET=C{c}");
        for b in members {
            // At most 16 entries per data line.
            let ids: Vec<String> = std::iter::once(eid)
                .chain(b.iter().map(|n| n + 1))
                .map(|v| v.to_string())
                .collect();
            let _ = writeln!(s, "{},", ids[..16].join(", "));
            let _ = writeln!(s, "{}", ids[16..].join(", "));
            eid += 1;
        }
    }
    let used: Vec<usize> = (0..n_classes)
        .filter(|c| mesh.bricks.iter().any(|(cl, _, _)| cl == c))
        .collect();
    s.push_str("*ELSET, ELSET=EALL\n");
    let _ = writeln!(
        s,
        "{}",
        used.iter()
            .map(|c| format!("C{c}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    s.push_str("*NSET, NSET=NTOP\n");
    let mut top: Vec<usize> = mesh.top.iter().flatten().map(|n| n + 1).collect();
    top.sort_unstable();
    top.dedup();
    for chunk in top.chunks(16) {
        let _ = writeln!(
            s,
            "{}",
            chunk
                .iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    // One element set per spring and per mass: CalculiX takes one value per set.
    for (i, sp) in load.springs.iter().enumerate() {
        if sp.to_fixture && load.fixture.is_some() {
            let _ = writeln!(
                s,
                "*ELEMENT, TYPE=SPRING2, ELSET=S{i}\n{}, {}, {fixture_node}\n*SPRING, ELSET=S{i}\n{},{}\n{}",
                eid,
                sp.node + 1,
                sp.dof,
                sp.dof,
                num(sp.k_n_per_mm)
            );
        } else {
            let _ = writeln!(
                s,
                "*ELEMENT, TYPE=SPRING1, ELSET=S{i}\n{}, {}\n*SPRING, ELSET=S{i}\n{}\n{}",
                eid,
                sp.node + 1,
                sp.dof,
                num(sp.k_n_per_mm)
            );
        }
        eid += 1;
    }
    if let Some(f) = &load.fixture {
        let _ = writeln!(
            s,
            "*ELEMENT, TYPE=SPRING1, ELSET=SFIX\n{eid}, {fixture_node}\n*SPRING, ELSET=SFIX\n3\n{}\n*ELEMENT, TYPE=MASS, ELSET=MFIX\n{}, {fixture_node}\n*MASS, ELSET=MFIX\n{}",
            num(f.k_n_per_mm),
            eid + 1,
            num(f.mass_t)
        );
        eid += 2;
    }
    for (i, m) in load.masses.iter().enumerate() {
        let _ = writeln!(
            s,
            "*ELEMENT, TYPE=MASS, ELSET=M{i}\n{}, {}\n*MASS, ELSET=M{i}\n{}",
            eid,
            m.node + 1,
            num(m.mass_t)
        );
        eid += 1;
    }
    if !load.fixed.is_empty() || load.fixture.is_some() {
        s.push_str("*BOUNDARY\n");
        for (n, dof) in &load.fixed {
            let _ = writeln!(s, "{}, {dof}, {dof}", n + 1);
        }
        if load.fixture.is_some() {
            let _ = writeln!(s, "{fixture_node}, 1, 2");
        }
    }
    for c in used {
        let m = &load.materials[c];
        let _ = writeln!(
            s,
            "*MATERIAL, NAME=MAT{c}\n*ELASTIC, TYPE=ENGINEERING CONSTANTS\n{}, {}, {}, {}, {}, {}, {}, {}\n{}, 293.\n*DENSITY\n{}\n*SOLID SECTION, ELSET=C{c}, MATERIAL=MAT{c}",
            num(m.e_mpa[0]),
            num(m.e_mpa[1]),
            num(m.e_mpa[2]),
            num(m.nu[0]),
            num(m.nu[1]),
            num(m.nu[2]),
            num(m.g_mpa[0]),
            num(m.g_mpa[1]),
            num(m.g_mpa[2]),
            num(m.rho_t_per_mm3)
        );
    }
    let _ = writeln!(
        s,
        "*STEP\n*FREQUENCY\n{}\n*NODE PRINT, NSET=NTOP\nU\n*EL PRINT, ELSET=EALL, TOTALS=ONLY\nEMAS\n*END STEP",
        load.n_modes
    );
    s
}

/// What the truth reads from a frequency step's `.dat` file, in the deck's units.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Results {
    /// Per mode: frequency, Hz (negative eigenvalues of rigid modes give 0).
    pub freq_hz: Vec<f64>,
    /// Per mode: participation factors (x, y, z translation; x, y, z rotation about the
    /// origin), modes normalised to unit modal mass.
    pub participation: Vec<[f64; 6]>,
    /// Per mode: z displacement of the printed nodes (0-based deck node − 1 → value).
    pub uz: Vec<Vec<(usize, f64)>>,
    /// Mass of the bricks (t), and ∫x², ∫y², ∫xy dm about the centre of gravity (t·mm²).
    pub mass_t: f64,
    pub second_moments_cog: [f64; 3],
    /// Centre of gravity, mm.
    pub cog_mm: [f64; 3],
}

fn floats(line: &str) -> Vec<f64> {
    line.split_whitespace()
        .filter_map(|t| t.parse::<f64>().ok())
        .collect()
}

/// Parse CalculiX's `.dat` output of the deck above.
pub fn parse_dat(text: &str) -> Result<Results, String> {
    let lines: Vec<&str> = text.lines().collect();
    let mut r = Results::default();
    let mut i = 0;
    let (mut have_mass, mut have_moments, mut have_cog) = (false, false, false);
    let mut in_disp = false;
    let next_values = |i: usize| -> Option<(usize, Vec<f64>)> {
        (i + 1..lines.len().min(i + 6))
            .map(|k| (k, floats(lines[k])))
            .find(|(_, v)| !v.is_empty())
    };
    while i < lines.len() {
        let l = lines[i];
        if l.contains("E I G E N V A L U E   O U T P U T") {
            in_disp = false;
            i += 1;
            // Skip to the first numeric row, then read until a non-numeric line.
            while i < lines.len() && floats(lines[i]).len() < 5 {
                i += 1;
            }
            while i < lines.len() {
                let v = floats(lines[i]);
                if v.len() < 5 {
                    break;
                }
                r.freq_hz.push(if v[1] > 0.0 { v[3] } else { 0.0 });
                i += 1;
            }
            continue;
        }
        if l.contains("P A R T I C I P A T I O N   F A C T O R S") {
            in_disp = false;
            i += 1;
            while i < lines.len() && floats(lines[i]).len() < 7 {
                i += 1;
            }
            while i < lines.len() {
                let v = floats(lines[i]);
                if v.len() < 7 {
                    break;
                }
                r.participation.push([v[1], v[2], v[3], v[4], v[5], v[6]]);
                i += 1;
            }
            continue;
        }
        if l.trim_start().starts_with("displacements (vx,vy,vz)") {
            r.uz.push(Vec::new());
            in_disp = true;
            i += 1;
            continue;
        }
        if l.trim_start().starts_with("total mass for set") && !have_mass {
            in_disp = false;
            if let Some((k, v)) = next_values(i) {
                r.mass_t = v[0];
                have_mass = true;
                i = k;
            }
        } else if l
            .trim_start()
            .starts_with("total mass moment of inertia about the center")
            && !have_moments
        {
            in_disp = false;
            if let Some((k, v)) = next_values(i) {
                if v.len() >= 4 {
                    r.second_moments_cog = [v[0], v[1], v[3]];
                }
                have_moments = true;
                i = k;
            }
        } else if l.trim_start().starts_with("center of gravity for set") && !have_cog {
            in_disp = false;
            if let Some((k, v)) = next_values(i) {
                if v.len() >= 3 {
                    r.cog_mm = [v[0], v[1], v[2]];
                }
                have_cog = true;
                i = k;
            }
        } else if in_disp {
            let v = floats(l);
            if v.len() == 4 {
                let node = v[0] as usize;
                if node >= 1 {
                    if let Some(last) = r.uz.last_mut() {
                        last.push((node - 1, v[3]));
                    }
                }
            } else if !l.trim().is_empty() {
                in_disp = false;
            }
        }
        i += 1;
    }
    if r.freq_hz.is_empty() {
        return Err("CalculiX output: expected an eigenvalue table, found none".into());
    }
    if r.participation.len() != r.freq_hz.len() || r.uz.len() != r.freq_hz.len() {
        return Err(format!(
            "CalculiX output: expected participation factors and displacements for each of {} modes, found {} and {}",
            r.freq_hz.len(),
            r.participation.len(),
            r.uz.len()
        ));
    }
    if r.mass_t <= 0.0 {
        return Err("CalculiX output: expected the total mass (EMAS), found none".into());
    }
    Ok(r)
}
