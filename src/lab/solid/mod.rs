//! The solid truth: the board as a layered 3D elastic body, solved by CalculiX on a gmsh
//! mesh, so that the virtual lab's truth is not hbmu's own plate model.
//!
//! Why this is independent of the updating model (`src/fem`): it shares no element, mesh,
//! quadrature or eigen-solver code with it. `fem` is a Kirchhoff plate (BFS elements on a
//! tensor grid, holes as cut cells, copper smeared into CLT stiffnesses, the joint a spring
//! layer); this truth is 3D elasticity in 20-node bricks (CalculiX C3D20, fully integrated: the
//! reduced C3D20R gave spurious local modes in the thin copper bricks; one brick per layer
//! through the core and one per copper layer), on an unstructured quadrilateral mesh from gmsh
//! that conforms to the outline, the holes, every copper region and cut-out and the clamped
//! annuli, eigen-solved by CalculiX. What it has that the plate lacks:
//! - transverse shear and rotary inertia, and the orthotropic FR-4's through-thickness
//!   properties (E_z, ν_xz, ν_yz, G_xz, G_yz; defaults from Ansys's PCB material table, see
//!   [`SolidOptions`]), which the plate cannot represent;
//! - copper as bricks of its own on the faces where it lies (a partial-coverage pour is a
//!   brick of proportionally reduced modulus and density), not folded into laminate terms;
//! - exact holes and region edges (a conforming mesh, not cut cells);
//! - the joint as a contact patch: the clamped annulus's bottom-face nodes on grounded z
//!   springs (the measurement's joint stiffness spread by area, HRZ-lumped) and on in-plane
//!   springs (friction; Mindlin's tangential share of that stiffness), with the screw head and washer riding on its top face as point masses
//!   (mass and, through their spread over the annulus, rotary inertia).
//!
//! This module is pure: it writes the gmsh script and the CalculiX deck and reads their
//! outputs; running the two programs is the caller's ([`Solver`], implemented in
//! `io::external`).

pub mod ccx;
pub mod geo;
pub mod mesh;
#[cfg(test)]
mod tests;

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::truth::ModeSet;
use crate::fem::Board;
use ccx::{Fixture, Loading, Material, PointMass, Spring};
use geo::Disc;
use mesh::{Layer, Mesh2, Mesh3};

/// Runs the external programs of the solid truth.
pub trait Solver: Send + Sync {
    /// Mesh a gmsh script; returns the mesh in gmsh's Abaqus-format output.
    fn mesh(&self, geo_script: &str) -> Result<String, String>;
    /// Run a CalculiX deck; returns its `.dat` output.
    fn solve(&self, deck: &str) -> Result<String, String>;
}

/// Options of the solid truth (scenario section `[truth.solid]`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SolidOptions {
    /// In-plane element size, m (holes and narrow features get smaller ones). 3 mm: the
    /// quadratic elements then hold the default board's in-band frequencies within 0.03 % of
    /// a 1.5 mm mesh (`benches/solid_truth.rs` measures it), below the measured frequencies'
    /// scatter between repeated measurements.
    pub element_size_m: f64,
    /// Bricks through the FR-4 core (quadratic in z each).
    pub core_layers: usize,
    /// FR-4 through-thickness properties the board file does not give. Defaults: the
    /// laminate of Ansys's PCB thermal-structural example (Ansys Workbench Technology
    /// Showcase, "PCB material properties"): E_z = 8 GPa, ν_yz = ν_xz = 0.3,
    /// G_yz = G_xz = 3.5 GPa.
    pub e_z_pa: f64,
    pub nu_xz: f64,
    pub nu_yz: f64,
    pub g_xz_pa: f64,
    pub g_yz_pa: f64,
    /// Mass riding on each clamped patch's top face, kg: the screw head and washer. Default
    /// 0.28 g: a steel M2.5 pan head (Ø 4.5 × 1.75 mm, 0.22 g) and an M2.5 washer (Ø 5/2.7 ×
    /// 0.5 mm, 0.06 g); the nut and shank sit in the fixture.
    pub riding_mass_kg: f64,
}

impl Default for SolidOptions {
    fn default() -> Self {
        SolidOptions {
            element_size_m: 3e-3,
            core_layers: 1,
            e_z_pa: 8.0e9,
            nu_xz: 0.3,
            nu_yz: 0.3,
            g_xz_pa: 3.5e9,
            g_yz_pa: 3.5e9,
            riding_mass_kg: 0.28e-3,
        }
    }
}

impl SolidOptions {
    /// Check every value; `Err((field, expected, found))`.
    pub fn check(&self) -> Result<(), (String, String, String)> {
        let pos = |f: &str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err((
                    format!("truth.solid.{f}"),
                    "a finite positive number".to_string(),
                    v.to_string(),
                ))
            }
        };
        pos("element_size_m", self.element_size_m)?;
        pos("e_z_pa", self.e_z_pa)?;
        pos("g_xz_pa", self.g_xz_pa)?;
        pos("g_yz_pa", self.g_yz_pa)?;
        if !(self.riding_mass_kg.is_finite() && self.riding_mass_kg >= 0.0) {
            return Err((
                "truth.solid.riding_mass_kg".into(),
                "a finite number >= 0".into(),
                self.riding_mass_kg.to_string(),
            ));
        }
        for (f, v) in [("nu_xz", self.nu_xz), ("nu_yz", self.nu_yz)] {
            if !(v.is_finite() && (-1.0..0.5).contains(&v)) {
                return Err((
                    format!("truth.solid.{f}"),
                    "a Poisson ratio in [-1, 0.5)".into(),
                    v.to_string(),
                ));
            }
        }
        if !(1..=4).contains(&self.core_layers) {
            return Err((
                "truth.solid.core_layers".into(),
                "1 to 4".into(),
                self.core_layers.to_string(),
            ));
        }
        Ok(())
    }
}

/// Tangential over normal stiffness of an elastic contact, 2(1 − ν)/(2 − ν) with ν = 0.3
/// (Mindlin, "Compliance of elastic bodies in contact", J. Appl. Mech. 16, 1949): the clamped
/// patch's friction holds the board in-plane through springs of this share of the joint's
/// normal stiffness, not rigidly.
const TANGENTIAL_OVER_NORMAL: f64 = 2.0 * (1.0 - 0.3) / (2.0 - 0.3);

/// A free solid's rigid-body modes, below its elastic ones: three in-plane, three out of it.
const FREE_RIGID_MODES: usize = 6;

/// What a brick class is made of.
#[derive(Clone, Copy, Debug, PartialEq)]
enum ClassKind {
    /// FR-4; `underfill`: inside the underfill disc.
    Core { underfill: bool },
    /// Copper layer `layer` of the board file at coverage `fraction`.
    Copper { layer: usize, fraction: f64 },
}

/// A clamped patch: bottom-face nodes with their share of the patch area, the nodes on the
/// clamp's edge, and top-face nodes with their share.
#[derive(Clone, Debug)]
struct Patch {
    bottom: Vec<(usize, f64)>,
    edge: Vec<usize>,
    top: Vec<(usize, f64)>,
    r_clamp_mm: f64,
}

/// The state of one solve: the board's draw, the joints', and which effects are on.
#[derive(Clone, Debug, PartialEq)]
pub struct State {
    pub e_x_pa: f64,
    pub e_y_pa: f64,
    pub g_xy_pa: f64,
    pub mass_scale: f64,
    /// Per joint (hole order), N/m; bolted only.
    pub k_joint_n_per_m: Vec<f64>,
    /// Extra rotational restraint of each clamp (a stiffer washer edge), N·m/rad.
    pub k_rot_nm_per_rad: Option<f64>,
    /// A point mass on the top face: (x, y) m, kg.
    pub point_mass: Option<([f64; 2], f64)>,
    /// Core stiffness factor inside the underfill disc (when the model has one).
    pub underfill_factor: Option<f64>,
    /// A compliant fixture between the joints and the shaker: (k N/m, mass kg).
    pub fixture: Option<(f64, f64)>,
    /// Elastic modes wanted.
    pub n_modes: usize,
}

/// The mesh and bookkeeping of one setup, ready for solves in any [`State`].
pub struct SolidModel {
    board: Board,
    opts: SolidOptions,
    bolted: bool,
    mesh2: Mesh2,
    mesh3: Mesh3,
    classes: Vec<ClassKind>,
    patches: Vec<Patch>,
    underfill: Option<Disc>,
    solver: Arc<dyn Solver>,
}

fn solid_err(msg: impl Into<String>) -> super::LabError {
    super::LabError::Solid(msg.into())
}

/// Copper coverage of layer `l` at point `p` (m): the largest fraction of the coverage
/// regions containing it less the largest of the cut-outs, within [0, 1].
fn coverage_at(board: &Board, l: usize, p: [f64; 2]) -> f64 {
    let layer = &board.copper[l];
    let cov = layer
        .coverage
        .iter()
        .filter(|r| r.contains(p[0], p[1]))
        .map(|r| r.fraction())
        .fold(0.0, f64::max);
    let cut = layer
        .cutouts
        .iter()
        .filter(|r| r.contains(p[0], p[1]))
        .map(|r| r.fraction())
        .fold(0.0, f64::max);
    (cov - cut).clamp(0.0, 1.0)
}

impl SolidModel {
    /// Mesh the board for a free (`bolted = false`) or bolted setup; `underfill` is a disc
    /// the mesh must conform to.
    pub fn build(
        board: &Board,
        opts: &SolidOptions,
        bolted: bool,
        underfill: Option<Disc>,
        solver: Arc<dyn Solver>,
    ) -> Result<SolidModel, super::LabError> {
        for (l, layer) in board.copper.iter().enumerate() {
            if !layer.density_maps.is_empty() || layer.gerber.is_some() {
                return Err(solid_err(format!(
                    "copper layer {} ({}): the solid truth takes copper as coverage regions and cut-outs; found a raster density map or a Gerber layer",
                    l + 1,
                    layer.name
                )));
            }
        }
        if bolted && board.holes.is_empty() {
            return Err(solid_err(
                "bolted setup: expected at least one hole in the board file",
            ));
        }
        let mut discs: Vec<Disc> = Vec::new();
        if bolted {
            for h in &board.holes {
                discs.push(Disc {
                    x_m: h.x_m,
                    y_m: h.y_m,
                    r_m: 0.5 * board.joint().clamp_diameter_m,
                });
            }
        }
        discs.extend(underfill);
        let script = geo::geo_script(board, opts.element_size_m, &discs);
        let text = solver.mesh(&script).map_err(solid_err)?;
        let mesh2 = mesh::parse_gmsh_inp(&text).map_err(solid_err)?;

        // Brick classes: the core (inside/outside the underfill disc), then each copper layer
        // at each coverage fraction found.
        let mut classes: Vec<ClassKind> = vec![
            ClassKind::Core { underfill: false },
            ClassKind::Core { underfill: true },
        ];
        let class_of = |k: ClassKind, classes: &mut Vec<ClassKind>| -> usize {
            match classes.iter().position(|c| *c == k) {
                Some(i) => i,
                None => {
                    classes.push(k);
                    classes.len() - 1
                }
            }
        };
        let centroids_m: Vec<[f64; 2]> = (0..mesh2.quads.len())
            .map(|e| {
                let c = mesh2.centroid(e);
                [1e-3 * c[0], 1e-3 * c[1]]
            })
            .collect();
        let in_disc = |d: &Disc, p: [f64; 2]| (p[0] - d.x_m).hypot(p[1] - d.y_m) < d.r_m;
        let h_mm = 1e3 * board.core.thickness_m;
        // Each copper layer's bricks: the class of its coverage over each element, if any.
        let copper_classes = |l: usize, classes: &mut Vec<ClassKind>| -> Vec<Option<usize>> {
            centroids_m
                .iter()
                .map(|&p| {
                    let fraction = coverage_at(board, l, p);
                    (fraction > 0.0)
                        .then(|| class_of(ClassKind::Copper { layer: l, fraction }, classes))
                })
                .collect()
        };
        let side_layers = |side: crate::fem::board::Side| {
            board
                .copper
                .iter()
                .enumerate()
                .filter(move |(_, c)| c.side == side)
                .map(|(l, c)| (l, 1e3 * c.thickness_m))
        };
        // Bottom copper: the board file's first bottom layer lies on the core, later ones
        // further out; listed here bottom-up.
        let mut z = -0.5 * h_mm;
        let mut below: Vec<Layer> = Vec::new();
        for (l, t) in side_layers(crate::fem::board::Side::Bottom) {
            below.push(Layer {
                z0_mm: z - t,
                z1_mm: z,
                class: copper_classes(l, &mut classes),
            });
            z -= t;
        }
        below.reverse();
        let mut layers: Vec<Layer> = below;
        let core_class: Vec<Option<usize>> = centroids_m
            .iter()
            .map(|&p| Some(usize::from(underfill.is_some_and(|d| in_disc(&d, p)))))
            .collect();
        for k in 0..opts.core_layers {
            let dz = h_mm / opts.core_layers as f64;
            layers.push(Layer {
                z0_mm: -0.5 * h_mm + k as f64 * dz,
                z1_mm: -0.5 * h_mm + (k + 1) as f64 * dz,
                class: core_class.clone(),
            });
        }
        let mut z = 0.5 * h_mm;
        for (l, t) in side_layers(crate::fem::board::Side::Top) {
            layers.push(Layer {
                z0_mm: z,
                z1_mm: z + t,
                class: copper_classes(l, &mut classes),
            });
            z += t;
        }
        let mesh3 = mesh::extrude(&mesh2, &layers);

        let mut patches = Vec::new();
        if bolted {
            for h in &board.holes {
                let (cx, cy) = (1e3 * h.x_m, 1e3 * h.y_m);
                let r_clamp_mm = 0.5e3 * board.joint().clamp_diameter_m;
                let mut w2 = vec![0.0; mesh2.xy_mm.len()];
                for e in 0..mesh2.quads.len() {
                    let c = mesh2.centroid(e);
                    if (c[0] - cx).hypot(c[1] - cy) < r_clamp_mm {
                        for (k, w) in mesh2.face_weights(e).iter().enumerate() {
                            w2[mesh2.quads[e][k]] += w;
                        }
                    }
                }
                let pick = |face: &[Option<usize>]| -> Vec<(usize, f64)> {
                    w2.iter()
                        .enumerate()
                        .filter(|(_, w)| **w > 0.0)
                        .filter_map(|(n, w)| face[n].map(|id| (id, *w)))
                        .collect()
                };
                let bottom = pick(&mesh3.bottom);
                let top = pick(&mesh3.top);
                let tol = 1e-3 * r_clamp_mm;
                let edge: Vec<usize> = w2
                    .iter()
                    .enumerate()
                    .filter(|(n, w)| {
                        let p = mesh2.xy_mm[*n];
                        **w > 0.0 && ((p[0] - cx).hypot(p[1] - cy) - r_clamp_mm).abs() < tol
                    })
                    .filter_map(|(n, _)| mesh3.bottom[n])
                    .collect();
                if bottom.is_empty() || edge.is_empty() {
                    return Err(solid_err(format!(
                        "the mesh has no clamped patch around the hole at ({:.1}, {:.1}) mm",
                        cx, cy
                    )));
                }
                patches.push(Patch {
                    bottom,
                    edge,
                    top,
                    r_clamp_mm,
                });
            }
        }
        Ok(SolidModel {
            board: board.clone(),
            opts: opts.clone(),
            bolted,
            mesh2,
            mesh3,
            classes,
            patches,
            underfill,
            solver,
        })
    }

    /// Number of nodes and bricks of the 3D mesh.
    pub fn size(&self) -> (usize, usize) {
        (self.mesh3.xyz_mm.len(), self.mesh3.bricks.len())
    }

    fn materials(&self, st: &State) -> Vec<Material> {
        let c = &self.board.core;
        let o = &self.opts;
        let rho = |r: f64| 1e-12 * r * st.mass_scale; // kg/m³ → t/mm³
        self.classes
            .iter()
            .map(|k| match *k {
                ClassKind::Core { underfill } => {
                    let f = if underfill {
                        st.underfill_factor.unwrap_or(1.0)
                    } else {
                        1.0
                    };
                    Material {
                        e_mpa: [1e-6 * f * st.e_x_pa, 1e-6 * f * st.e_y_pa, 1e-6 * o.e_z_pa],
                        nu: [c.nu_xy, o.nu_xz, o.nu_yz],
                        g_mpa: [1e-6 * f * st.g_xy_pa, 1e-6 * o.g_xz_pa, 1e-6 * o.g_yz_pa],
                        rho_t_per_mm3: rho(c.density_kg_per_m3),
                    }
                }
                ClassKind::Copper { layer, fraction } => {
                    let cu = &self.board.copper[layer];
                    Material::isotropic(
                        1e-6 * fraction * cu.e_pa,
                        cu.nu,
                        rho(fraction * cu.density_kg_per_m3),
                    )
                }
            })
            .collect()
    }

    fn nearest_top_node(&self, p_m: [f64; 2]) -> Option<usize> {
        let p = [1e3 * p_m[0], 1e3 * p_m[1]];
        self.mesh3
            .top
            .iter()
            .enumerate()
            .filter_map(|(n, t)| t.map(|id| (n, id)))
            .min_by(|a, b| {
                let d = |n: usize| {
                    let q = self.mesh2.xy_mm[n];
                    (q[0] - p[0]).hypot(q[1] - p[1])
                };
                d(a.0).total_cmp(&d(b.0))
            })
            .map(|(_, id)| id)
    }

    /// The loading of a solve in state `st`.
    fn loading(
        &self,
        st: &State,
        shaker_reference_m: [f64; 3],
    ) -> Result<Loading, super::LabError> {
        let mut load = Loading {
            materials: self.materials(st),
            n_modes: st.n_modes + if self.bolted { 0 } else { FREE_RIGID_MODES },
            ..Loading::default()
        };
        if self.bolted {
            if st.k_joint_n_per_m.len() != self.patches.len() {
                return Err(solid_err(format!(
                    "expected {} joint stiffnesses, found {}",
                    self.patches.len(),
                    st.k_joint_n_per_m.len()
                )));
            }
            // The fixture moves in z under the joints, at the shaker's reference point.
            load.fixture = st.fixture.map(|(k, m)| Fixture {
                at_mm: [
                    1e3 * shaker_reference_m[0],
                    1e3 * shaker_reference_m[1],
                    1e3 * shaker_reference_m[2],
                ],
                k_n_per_mm: 1e-3 * k,
                mass_t: 1e-3 * m,
            });
            for (p, &k) in self.patches.iter().zip(&st.k_joint_n_per_m) {
                let w: f64 = p.bottom.iter().map(|(_, w)| w).sum();
                for &(node, wi) in &p.bottom {
                    let kz = 1e-3 * k * wi / w;
                    load.springs.push(Spring {
                        node,
                        dof: 3,
                        k_n_per_mm: kz,
                        to_fixture: true,
                    });
                    for dof in [1, 2] {
                        load.springs.push(Spring {
                            node,
                            dof,
                            k_n_per_mm: TANGENTIAL_OVER_NORMAL * kz,
                            to_fixture: false,
                        });
                    }
                }
                if let Some(k_rot) = st.k_rot_nm_per_rad {
                    // A ring of springs of total stiffness K at radius r restrains rotation
                    // about any in-plane axis through the centre by K r² / 2.
                    let r_m = 1e-3 * p.r_clamp_mm;
                    let k_ring = 2.0 * k_rot / (r_m * r_m);
                    for &node in &p.edge {
                        load.springs.push(Spring {
                            node,
                            dof: 3,
                            k_n_per_mm: 1e-3 * k_ring / p.edge.len() as f64,
                            to_fixture: true,
                        });
                    }
                }
                let wt: f64 = p.top.iter().map(|(_, w)| w).sum();
                if self.opts.riding_mass_kg > 0.0 {
                    for &(node, wi) in &p.top {
                        load.masses.push(PointMass {
                            node,
                            mass_t: 1e-3 * self.opts.riding_mass_kg * wi / wt,
                        });
                    }
                }
            }
        }
        if let Some((p, m)) = st.point_mass {
            let node = self
                .nearest_top_node(p)
                .ok_or_else(|| solid_err("the mesh has no top face"))?;
            load.masses.push(PointMass {
                node,
                mass_t: 1e-3 * m,
            });
        }
        if st.underfill_factor.is_some() && self.underfill.is_none() {
            return Err(solid_err(
                "an underfill stiffness was given but the mesh has no underfill disc",
            ));
        }
        Ok(load)
    }

    /// Solve for the modes in state `st`, with shapes at `points_m` (on the board, not in a
    /// hole), in SI: the top face's z displacement, mass-normalised; free: the rigid-body
    /// shapes (translation and the two rotations about the centre of gravity); bolted: the
    /// rocking participations from HRZ-lumped nodal masses; the mass of the board's bricks
    /// plus any point mass on it (not the riding screw heads). `shaker_reference_m`: the point the rocking participations are taken about,
    /// where a compliant fixture's mass sits.
    pub fn modes(
        &self,
        st: &State,
        points_m: &[[f64; 2]],
        shaker_reference_m: [f64; 3],
    ) -> Result<ModeSet, super::LabError> {
        let located: Vec<(usize, [f64; 2])> = points_m
            .iter()
            .map(|p| {
                self.mesh2.locate([1e3 * p[0], 1e3 * p[1]]).ok_or_else(|| {
                    solid_err(format!(
                        "scan point ({:.2}, {:.2}) mm lies off the board or in a hole",
                        1e3 * p[0],
                        1e3 * p[1]
                    ))
                })
            })
            .collect::<Result<_, _>>()?;
        let load = self.loading(st, shaker_reference_m)?;
        let deck = ccx::deck(&self.mesh3, &load);
        let dat = self.solver.solve(&deck).map_err(solid_err)?;
        let res = ccx::parse_dat(&dat).map_err(solid_err)?;
        // Mode r's z displacement of the top face per 2D node.
        let n2 = self.mesh2.xy_mm.len();
        let mut top_of3 = vec![usize::MAX; self.mesh3.xyz_mm.len()];
        for (n, t) in self.mesh3.top.iter().enumerate() {
            if let Some(id) = t {
                top_of3[*id] = n;
            }
        }
        // ccx normalises to unit modal mass in t·mm²: ψ_SI = φ / √1000 (1/√kg);
        // Γ_SI = √1000 Γ (√kg).
        let to_si = 1.0 / 1000f64.sqrt();
        let first = if self.bolted { 0 } else { FREE_RIGID_MODES };
        if res.freq_hz.len() < first + st.n_modes {
            return Err(solid_err(format!(
                "CalculiX returned {} modes, expected {}",
                res.freq_hz.len(),
                first + st.n_modes
            )));
        }
        // Nodal masses (HRZ over each element's areal density) for the rocking terms.
        let node_mass_t = if self.bolted {
            self.node_masses(&load)
        } else {
            vec![]
        };
        let (xr, yr) = (1e3 * shaker_reference_m[0], 1e3 * shaker_reference_m[1]);
        let mut out = ModeSet {
            freq_hz: vec![],
            shapes: vec![],
            gamma: vec![],
            gamma_rock: vec![],
            rigid: vec![],
            total_mass_kg: 1e3 * res.mass_t + st.point_mass.map_or(0.0, |(_, m)| m),
        };
        for r in first..first + st.n_modes {
            let mut field = vec![0.0; n2];
            for &(node3, uz) in &res.uz[r] {
                if let Some(&n) = top_of3.get(node3) {
                    if n != usize::MAX {
                        field[n] = uz;
                    }
                }
            }
            out.freq_hz.push(res.freq_hz[r]);
            out.shapes.push(
                located
                    .iter()
                    .map(|&(e, xi)| to_si * self.mesh2.interpolate(&field, e, xi))
                    .collect(),
            );
            if self.bolted {
                out.gamma.push(1000f64.sqrt() * res.participation[r][2]);
                let (mut gx, mut gy) = (0.0, 0.0);
                for (n, m) in node_mass_t.iter().enumerate() {
                    let p = self.mesh2.xy_mm[n];
                    gx += m * (p[0] - xr) * field[n];
                    gy += m * (p[1] - yr) * field[n];
                }
                // t·mm·mm → kg·m·m with ψ_SI = φ/√1000: × 1e3 · 1e-3 · 1e-3 / √1000.
                let f = 1e-3 * to_si;
                out.gamma_rock.push([f * gx, f * gy]);
            }
        }
        if !self.bolted {
            let m = 1e3 * res.mass_t;
            let [ixx, iyy, ixy] = res.second_moments_cog.map(|v| 1e-3 * v);
            let (xc, yc) = (1e-3 * res.cog_mm[0], 1e-3 * res.cog_mm[1]);
            let n3 = (iyy - ixy * ixy / ixx).sqrt();
            out.rigid = vec![
                points_m.iter().map(|_| 1.0 / m.sqrt()).collect(),
                points_m.iter().map(|p| (p[0] - xc) / ixx.sqrt()).collect(),
                points_m
                    .iter()
                    .map(|p| ((p[1] - yc) - ixy / ixx * (p[0] - xc)) / n3)
                    .collect(),
            ];
        }
        Ok(out)
    }

    /// Lumped mass per 2D node, t: each element's areal density (its bricks) spread by its
    /// HRZ face weights, plus the point masses of the loading at their nodes.
    fn node_masses(&self, load: &Loading) -> Vec<f64> {
        let mut m = vec![0.0; self.mesh2.xy_mm.len()];
        let n_e = self.mesh2.quads.len();
        let mut areal = vec![0.0; n_e];
        for (class, e, b) in &self.mesh3.bricks {
            let t = self.mesh3.xyz_mm[b[4]][2] - self.mesh3.xyz_mm[b[0]][2];
            areal[*e] += load.materials[*class].rho_t_per_mm3 * t;
        }
        for (e, q) in self.mesh2.quads.iter().enumerate() {
            for (k, w) in self.mesh2.face_weights(e).iter().enumerate() {
                m[q[k]] += areal[e] * w;
            }
        }
        let mut node2 = vec![usize::MAX; self.mesh3.xyz_mm.len()];
        for face in [&self.mesh3.top, &self.mesh3.bottom] {
            for (n, t) in face.iter().enumerate() {
                if let Some(id) = t {
                    node2[*id] = n;
                }
            }
        }
        for pm in &load.masses {
            if let Some(&n) = node2.get(pm.node) {
                if n != usize::MAX {
                    m[n] += pm.mass_t;
                }
            }
        }
        m
    }
}
