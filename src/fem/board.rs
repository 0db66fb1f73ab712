//! Board description: the plain-data input of the physics core (outline, FR-4 core,
//! copper layers with their coverage maps, bolt holes, joint data, default scan grid),
//! parsed from TOML (`Board::from_toml_str`) and checked for physical sense.
//!
//! Frame: origin at a board corner, x along the long edge, y along the short edge,
//! z normal to the board (the frame of `shared/campaign-format.md`). All lengths in
//! metres, moduli in pascals, densities in kg/m³.

use serde::{Deserialize, Serialize};

use super::geometry::{polygon_rect_area, signed_area, triangulate, Rect};
use super::FemError;

/// The TOML text of the default board (`data/boards/default.toml`), compiled in so the
/// CLI can run without `--board`.
pub const DEFAULT_BOARD_TOML: &str = include_str!("../../data/boards/default.toml");

/// A printed circuit board: an orthotropic FR-4 core with copper layers, bolted at holes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Board {
    /// Free-text name of the design, e.g. `"paper-pcb"`.
    pub name: String,
    /// Outline length along x, m.
    pub length_x_m: f64,
    /// Outline width along y, m.
    pub width_y_m: f64,
    /// FR-4 core (the mid-plane laminate).
    pub core: CoreMaterial,
    /// Copper layers, any number (0 allowed).
    #[serde(default)]
    pub copper: Vec<CopperLayer>,
    /// Bolt holes (through holes of the bolted joints).
    #[serde(default)]
    pub holes: Vec<Hole>,
    /// Bolted-joint data shared by all holes (`[joint]`): required where the board has holes,
    /// optional for a board without (it has no bolted setup).
    #[serde(default)]
    pub joint: Option<JointData>,
    /// Default mesh density.
    pub mesh: MeshOptions,
    /// Mesh of the bolted setups, where one differs from `mesh` (`[mesh_bolted]`): the
    /// deformation around a small, stiff clamp varies over a few millimetres, so bolted
    /// modes need a finer mesh than free-free ones for the same discretization error (see
    /// `hbmu fe modes`, which estimates it per setup). Absent: `mesh`.
    #[serde(default)]
    pub mesh_bolted: Option<MeshOptions>,
    /// Default scan grid on which the CLI reports mode shapes.
    pub scan_grid: ScanGrid,
    /// Gerber import options (board outline, frame, raster resolution), for copper
    /// layers that name a Gerber file.
    #[serde(default)]
    pub gerber: Option<GerberOptions>,
}

fn default_gerber_resolution_m() -> f64 {
    1e-4
}

/// How Gerber files map onto the board (`[gerber]` in the TOML).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GerberOptions {
    /// Board profile (outline) Gerber file, relative to the board file. The bounding box
    /// of its drawn centre-lines is the board edge: its lower-left corner is the board
    /// origin, and its size must equal `length_x_m × width_y_m` (within 0.1 mm).
    #[serde(default)]
    pub outline: Option<String>,
    /// Gerber coordinates of the board's lower-left corner, m, when there is no outline
    /// file (default: the Gerber origin).
    #[serde(default)]
    pub origin_m: Option<[f64; 2]>,
    /// Largest sub-cell size on which each element integrates a Gerber layer's
    /// coverage, m (the element is cut into equal sub-cells no larger than this).
    #[serde(default = "default_gerber_resolution_m")]
    pub resolution_m: f64,
}

/// Orthotropic FR-4 core, principal axes along x and y.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoreMaterial {
    /// Core thickness, m.
    pub thickness_m: f64,
    /// Young's modulus along x, Pa.
    pub e_x_pa: f64,
    /// Young's modulus along y, Pa.
    pub e_y_pa: f64,
    /// In-plane shear modulus, Pa.
    pub g_xy_pa: f64,
    /// Major Poisson ratio ν_xy (strain in y per strain in x under σ_x), dimensionless.
    pub nu_xy: f64,
    /// Density, kg/m³.
    pub density_kg_per_m3: f64,
    /// Transverse shear modulus in the x–z plane, Pa. Given (with `g_yz_pa`), the board is a
    /// shear-deformable (Mindlin–Reissner) plate with rotary inertia ([`super::mindlin`]);
    /// absent, a Kirchhoff plate.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub g_xz_pa: Option<f64>,
    /// Transverse shear modulus in the y–z plane, Pa (see `g_xz_pa`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub g_yz_pa: Option<f64>,
}

impl Board {
    /// What the board's plate model leaves out, for the diagnosis's model-form sentence.
    pub fn model_form(&self) -> &'static str {
        if self.core.transverse_shear().is_some() {
            "a first-order shear-deformable plate, its transverse shear stiffness Whitney's for the nominal stack, copper homogenised into the laminate, no through-thickness normal strain"
        } else {
            "a thin plate without transverse shear and rotary inertia, copper homogenised into the laminate"
        }
    }
}

impl CoreMaterial {
    /// The transverse shear moduli (G_xz, G_yz), Pa, when the plate is shear-deformable.
    pub fn transverse_shear(&self) -> Option<(f64, f64)> {
        self.g_xz_pa.zip(self.g_yz_pa)
    }
}

/// Which face of the core a copper layer is bonded to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Side {
    /// z > 0 face.
    Top,
    /// z < 0 face.
    Bottom,
}

/// An isotropic copper layer on one face, with the region it covers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CopperLayer {
    /// Layer name, e.g. `"top"`.
    pub name: String,
    /// Face it lies on.
    pub side: Side,
    /// Layer thickness, m.
    pub thickness_m: f64,
    /// Young's modulus, Pa.
    pub e_pa: f64,
    /// Poisson ratio.
    pub nu: f64,
    /// Density, kg/m³.
    pub density_kg_per_m3: f64,
    /// Covered regions, each with its coverage fraction (overlaps take the maximum).
    #[serde(default)]
    pub coverage: Vec<Region>,
    /// Subtractive regions (plane cut-outs, anti-pads), each removing its `fraction`
    /// of copper where it lies; the result is capped to [0, 1].
    #[serde(default)]
    pub cutouts: Vec<Region>,
    /// Raster copper-density maps (e.g. exported from ECAD), combined with the
    /// coverage regions by the maximum (cut-outs still subtract).
    #[serde(default)]
    pub density_maps: Vec<DensityMap>,
    /// Gerber RS-274X file of this layer (relative to the board file), integrated on a
    /// sub-grid of each element (see `[gerber]`) and combined like a density map.
    #[serde(default)]
    pub gerber: Option<String>,
    /// The image read from `gerber` by `io::board_files`, in the board frame (not part
    /// of the TOML).
    #[serde(skip)]
    pub gerber_image: Option<std::sync::Arc<GerberLayerImage>>,
}

/// A Gerber layer's image in the board frame, with the raster cell its coverage is
/// integrated on inside each element.
#[derive(Clone, Debug, PartialEq)]
pub struct GerberLayerImage {
    /// Dark and clear features, m, board frame.
    pub image: super::gerber::Image,
    /// Largest sub-cell size inside an element, m (`[gerber] resolution_m`).
    pub resolution_m: f64,
}

/// A raster copper-density map: a grid of cells over `[x0, x1] × [y0, y1]`, each with
/// the fraction of its area that is copper, constant over the cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DensityMap {
    /// CSV file, relative to the board file: one line per row of cells from `y0_m`
    /// upward (first line lowest), one comma-separated fraction in [0, 1] per cell
    /// from `x0_m` rightward; lines starting with `#` are comments.
    pub file: String,
    /// Extent: lower x, m.
    pub x0_m: f64,
    /// Lower y, m.
    pub y0_m: f64,
    /// Upper x, m.
    pub x1_m: f64,
    /// Upper y, m.
    pub y1_m: f64,
    /// The grid, read from `file` by `io::board` (not part of the TOML).
    #[serde(skip)]
    pub grid: Option<Grid>,
}

/// Values of a raster, row-major from the lowest row: `values[j * nx + i]` is cell
/// (i, j), i along x.
#[derive(Clone, Debug, PartialEq)]
pub struct Grid {
    /// Cells along x.
    pub nx: usize,
    /// Cells along y.
    pub ny: usize,
    /// Fractions in [0, 1].
    pub values: Vec<f64>,
}

fn one() -> f64 {
    1.0
}

fn is_one(v: &f64) -> bool {
    *v == 1.0
}

/// A region of copper.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum Region {
    /// Axis-aligned rectangle `[x0, x1] × [y0, y1]`, m.
    Rect {
        /// Lower x, m.
        x0_m: f64,
        /// Lower y, m.
        y0_m: f64,
        /// Upper x, m.
        x1_m: f64,
        /// Upper y, m.
        y1_m: f64,
        /// Fraction of the region that is copper (hatched pours, smeared pad rows;
        /// 1 = solid), or removed by it for a cut-out.
        #[serde(default = "one", skip_serializing_if = "is_one")]
        fraction: f64,
    },
    /// Simple polygon, vertices `[x, y]` in m, either orientation.
    Polygon {
        /// Vertices in order.
        vertices_m: Vec<[f64; 2]>,
        /// As for `Rect`.
        #[serde(default = "one", skip_serializing_if = "is_one")]
        fraction: f64,
    },
}

impl Region {
    /// The region's boundary as vertices in order (a rectangle's four corners).
    pub fn outline(&self) -> Vec<[f64; 2]> {
        match self {
            Region::Rect {
                x0_m,
                y0_m,
                x1_m,
                y1_m,
                ..
            } => vec![
                [*x0_m, *y0_m],
                [*x1_m, *y0_m],
                [*x1_m, *y1_m],
                [*x0_m, *y1_m],
            ],
            Region::Polygon { vertices_m, .. } => vertices_m.clone(),
        }
    }

    /// The region's copper (or removal) fraction.
    pub fn fraction(&self) -> f64 {
        match self {
            Region::Rect { fraction, .. } | Region::Polygon { fraction, .. } => *fraction,
        }
    }

    /// Exact area of the region inside `r`, m² (polygon clipping).
    pub fn area_in(&self, r: &Rect) -> f64 {
        match self {
            Region::Rect {
                x0_m,
                y0_m,
                x1_m,
                y1_m,
                ..
            } => {
                let w = (x1_m.min(r.x1) - x0_m.max(r.x0)).max(0.0);
                let h = (y1_m.min(r.y1) - y0_m.max(r.y0)).max(0.0);
                w * h
            }
            Region::Polygon { vertices_m, .. } => polygon_rect_area(vertices_m, r),
        }
    }

    fn check(&self, what: &str) -> Result<(), FemError> {
        let f = self.fraction();
        if !(0.0..=1.0).contains(&f) {
            return Err(FemError::BoardInvalid(format!(
                "{what}.fraction: expected 0 <= fraction <= 1, found {f}"
            )));
        }
        match self {
            Region::Rect {
                x0_m,
                y0_m,
                x1_m,
                y1_m,
                ..
            } => {
                if !(x0_m < x1_m && y0_m < y1_m) {
                    return Err(FemError::BoardInvalid(format!(
                        "{what}: expected x0_m < x1_m and y0_m < y1_m, found [{x0_m}, {x1_m}] × [{y0_m}, {y1_m}]"
                    )));
                }
            }
            Region::Polygon { vertices_m, .. } => {
                if vertices_m.len() < 3 || vertices_m.iter().flatten().any(|v| !v.is_finite()) {
                    return Err(FemError::BoardInvalid(format!(
                        "{what}: expected a polygon of at least 3 finite vertices, found {} vertices",
                        vertices_m.len()
                    )));
                }
                // A simple polygon is covered exactly by its ear-clipped triangles; a
                // self-intersecting one is not.
                let area = signed_area(vertices_m).abs();
                let tri: f64 = triangulate(vertices_m)
                    .iter()
                    .map(|t| signed_area(t).abs())
                    .sum();
                if !(area > 0.0 && (tri - area).abs() <= 1e-9 * area) {
                    return Err(FemError::BoardInvalid(format!(
                        "{what}: expected a simple (not self-intersecting) polygon of positive area, found area {area:e} m² whose triangulation covers {tri:e} m²"
                    )));
                }
            }
        }
        Ok(())
    }

    /// Whether point (x, y) lies inside (even–odd rule for polygons).
    pub fn contains(&self, x: f64, y: f64) -> bool {
        match self {
            Region::Rect {
                x0_m,
                y0_m,
                x1_m,
                y1_m,
                ..
            } => x >= *x0_m && x <= *x1_m && y >= *y0_m && y <= *y1_m,
            Region::Polygon { vertices_m, .. } => {
                let n = vertices_m.len();
                let mut inside = false;
                let mut j = n.wrapping_sub(1);
                for i in 0..n {
                    let [xi, yi] = vertices_m[i];
                    let [xj, yj] = vertices_m[j];
                    if (yi > y) != (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi {
                        inside = !inside;
                    }
                    j = i;
                }
                inside
            }
        }
    }
}

/// A bolt hole with its clamped patch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Hole {
    /// Centre x, m.
    pub x_m: f64,
    /// Centre y, m.
    pub y_m: f64,
    /// Hole diameter, m.
    pub diameter_m: f64,
}

/// Bolted-joint data common to all holes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JointData {
    /// Outer diameter of the clamped annulus (bolt head / washer / nut contact), m.
    pub clamp_diameter_m: f64,
    /// Nominal total out-of-plane contact stiffness of one joint (head and nut
    /// contacts in parallel), N/m.
    pub k_con_n_per_m: f64,
    /// Mass of one bolt with nut and washers, kg (used by the joint-mass variant).
    pub bolt_mass_kg: f64,
    /// Tangential over normal stiffness of the clamped contact. A stuck (not slipping)
    /// contact holds the board's faces in-plane as well as out of it; the in-plane springs
    /// act half the board's thickness from its mid-plane, so they restrain the slopes by
    /// `tangential_over_normal × k_con × (h/2)²` per joint and axis
    /// ([`crate::fem::joints`]). Default Mindlin's 2(1 − ν)/(2 − ν) at ν = 0.3 (steel, and
    /// FR-4 through its thickness): 0.82. 0 leaves the contact free to slide.
    #[serde(default = "JointData::mindlin_tangential_over_normal")]
    pub tangential_over_normal: f64,
}

impl JointData {
    /// Mindlin's tangential over normal compliance ratio of an elastic contact at ν = 0.3
    /// ("Compliance of elastic bodies in contact", J. Appl. Mech. 16, 1949).
    pub fn mindlin_tangential_over_normal() -> f64 {
        2.0 * (1.0 - 0.3) / (2.0 - 0.3)
    }
}

/// Structured mesh density: `nx × ny` Bogner–Fox–Schmit rectangles.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MeshOptions {
    /// Elements along x.
    pub nx: usize,
    /// Elements along y.
    pub ny: usize,
}

/// Regular scan grid `nx × ny` points inset by `margin_m` from the edges.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScanGrid {
    /// Points along x.
    pub nx: usize,
    /// Points along y.
    pub ny: usize,
    /// Inset from every edge, m.
    pub margin_m: f64,
}

impl Board {
    /// The bolted-joint data, for the bolted setup. A bolted model needs holes, and a valid
    /// board with holes has `[joint]` ([`Board::validate`]), so every bolted path has it.
    pub fn joint(&self) -> &JointData {
        self.joint
            .as_ref()
            .expect("a board with holes has [joint] (Board::validate), and only a board with holes is bolted")
    }

    /// The thickness of all copper layers together, m: what a micrometer reading over the
    /// copper adds to the core (the sheet's `thickness_mm` is such a reading).
    pub fn copper_thickness_m(&self) -> f64 {
        self.copper.iter().map(|l| l.thickness_m).sum()
    }

    /// The mesh of a setup: `mesh_bolted` for bolted setups where the board has one.
    pub fn mesh_for(&self, setup: &crate::fem::model::Setup) -> &MeshOptions {
        match (setup, &self.mesh_bolted) {
            (crate::fem::model::Setup::Bolted(_), Some(m)) => m,
            _ => &self.mesh,
        }
    }

    /// The axis-parallel edges of the copper, where the bending stiffness jumps: the
    /// interfaces at x = const (edges running along y) and at y = const, for the mesh to
    /// put node lines on ([`super::grading::snap_to_interfaces`]). Each edge of a
    /// rectangle or polygon side (coverage or cut-out) is weighted by its length × the
    /// copper fraction across it × the layer's membrane stiffness t·E; a density map gives
    /// each cell boundary, weighted by the change of fraction across it summed over its
    /// cells × their length × t·E (interfaces of zero weight are ignored). Slanted polygon
    /// sides and Gerber layers give none: their jumps stay inside elements, converging O(h)
    /// (see `fem::convergence`).
    pub fn copper_interfaces(
        &self,
    ) -> (
        Vec<super::grading::Interface>,
        Vec<super::grading::Interface>,
    ) {
        use super::grading::Interface;
        let (mut at_x, mut at_y) = (vec![], vec![]);
        for layer in &self.copper {
            // (corner, next corner, copper fraction across the side)
            let mut sides: Vec<([f64; 2], [f64; 2], f64)> = vec![];
            let mut add_outline = |v: Vec<[f64; 2]>, frac: f64| {
                let n = v.len();
                sides.extend((0..n).map(|i| (v[i], v[(i + 1) % n], frac)));
            };
            for r in layer.coverage.iter().chain(&layer.cutouts) {
                add_outline(r.outline(), r.fraction());
            }
            let stiff = layer.thickness_m * layer.e_pa;
            for d in &layer.density_maps {
                let Some(g) = &d.grid else {
                    let extent = Region::Rect {
                        x0_m: d.x0_m,
                        y0_m: d.y0_m,
                        x1_m: d.x1_m,
                        y1_m: d.y1_m,
                        fraction: 1.0,
                    };
                    add_outline(extent.outline(), 1.0);
                    continue;
                };
                // Every cell boundary across which the fraction changes (the map's edge
                // against no copper included), weighted by the change × its length.
                let v = |i: usize, j: usize| g.values[j * g.nx + i];
                let (dx, dy) = (
                    (d.x1_m - d.x0_m) / g.nx as f64,
                    (d.y1_m - d.y0_m) / g.ny as f64,
                );
                let at = |lo: f64, hi: f64, n: usize, k: usize| {
                    if k == n {
                        hi
                    } else {
                        lo + k as f64 * (hi - lo) / n as f64
                    }
                };
                // The change across boundary k of n cells along one axis, summed over the
                // m cells across it (cell(k, l): k along, l across).
                let jumps = |n: usize, m: usize, cell: &dyn Fn(usize, usize) -> f64| {
                    (0..=n)
                        .map(|k| {
                            (0..m)
                                .map(|l| {
                                    let before = if k == 0 { 0.0 } else { cell(k - 1, l) };
                                    let after = if k == n { 0.0 } else { cell(k, l) };
                                    (after - before).abs()
                                })
                                .sum::<f64>()
                        })
                        .collect::<Vec<f64>>()
                };
                for (i, jump) in jumps(g.nx, g.ny, &|i, j| v(i, j)).into_iter().enumerate() {
                    at_x.push(Interface {
                        at_m: at(d.x0_m, d.x1_m, g.nx, i),
                        weight: stiff * jump * dy,
                    });
                }
                for (j, jump) in jumps(g.ny, g.nx, &|j, i| v(i, j)).into_iter().enumerate() {
                    at_y.push(Interface {
                        at_m: at(d.y0_m, d.y1_m, g.ny, j),
                        weight: stiff * jump * dx,
                    });
                }
            }
            for (a, b, frac) in sides {
                let w = stiff * frac.abs();
                if a[0] == b[0] {
                    at_x.push(Interface {
                        at_m: a[0],
                        weight: w * (b[1] - a[1]).abs(),
                    });
                } else if a[1] == b[1] {
                    at_y.push(Interface {
                        at_m: a[1],
                        weight: w * (b[0] - a[0]).abs(),
                    });
                }
            }
        }
        (at_x, at_y)
    }

    /// Parse and validate a board from TOML text. A board with density maps needs
    /// their files: read it with `io::board_files::read_board` instead.
    pub fn from_toml_str(text: &str) -> Result<Board, FemError> {
        let b = Board::from_toml_str_unvalidated(text)?;
        b.validate()?;
        Ok(b)
    }

    /// Parse a board from TOML text without validating it (density maps not read).
    pub fn from_toml_str_unvalidated(text: &str) -> Result<Board, FemError> {
        toml::from_str(text).map_err(|e| FemError::BoardParse(e.to_string()))
    }

    /// The compiled-in default board (paper-like, about 13 g).
    pub fn default_board() -> Board {
        // The default file is part of the crate and covered by a test.
        Board::from_toml_str(DEFAULT_BOARD_TOML)
            .unwrap_or_else(|e| unreachable!("data/boards/default.toml is invalid: {e}"))
    }

    /// Check every quantity for physical sense; errors name field, expected, found.
    pub fn validate(&self) -> Result<(), FemError> {
        let pos = |field: &str, v: f64| -> Result<(), FemError> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(FemError::BoardInvalid(format!(
                    "{field}: expected a finite positive number, found {v}"
                )))
            }
        };
        pos("length_x_m", self.length_x_m)?;
        pos("width_y_m", self.width_y_m)?;
        let c = &self.core;
        pos("core.thickness_m", c.thickness_m)?;
        pos("core.e_x_pa", c.e_x_pa)?;
        pos("core.e_y_pa", c.e_y_pa)?;
        pos("core.g_xy_pa", c.g_xy_pa)?;
        pos("core.density_kg_per_m3", c.density_kg_per_m3)?;
        match (c.g_xz_pa, c.g_yz_pa) {
            (Some(gx), Some(gy)) => {
                pos("core.g_xz_pa", gx)?;
                pos("core.g_yz_pa", gy)?;
            }
            (None, None) => {}
            _ => {
                return Err(FemError::BoardInvalid(
                    "core: expected both transverse shear moduli g_xz_pa and g_yz_pa (a shear-deformable plate) or neither (a Kirchhoff plate), found one".into(),
                ))
            }
        }
        let nu_yx = c.nu_xy * c.e_y_pa / c.e_x_pa;
        if !(c.nu_xy.is_finite() && c.nu_xy * nu_yx < 1.0 && c.nu_xy > -1.0) {
            return Err(FemError::BoardInvalid(format!(
                "core.nu_xy: expected ν_xy·ν_yx < 1 (positive-definite compliance), found ν_xy = {}",
                c.nu_xy
            )));
        }
        for (i, l) in self.copper.iter().enumerate() {
            pos(&format!("copper[{i}].thickness_m"), l.thickness_m)?;
            pos(&format!("copper[{i}].e_pa"), l.e_pa)?;
            pos(
                &format!("copper[{i}].density_kg_per_m3"),
                l.density_kg_per_m3,
            )?;
            for (k, r) in l.coverage.iter().enumerate() {
                r.check(&format!("copper[{i}].coverage[{k}]"))?;
            }
            for (k, r) in l.cutouts.iter().enumerate() {
                r.check(&format!("copper[{i}].cutouts[{k}]"))?;
            }
            for (k, d) in l.density_maps.iter().enumerate() {
                let what = format!("copper[{i}].density_maps[{k}] ({})", d.file);
                if !(d.x0_m < d.x1_m && d.y0_m < d.y1_m) {
                    return Err(FemError::BoardInvalid(format!(
                        "{what}: expected x0_m < x1_m and y0_m < y1_m, found [{}, {}] × [{}, {}]",
                        d.x0_m, d.x1_m, d.y0_m, d.y1_m
                    )));
                }
                let Some(g) = &d.grid else {
                    return Err(FemError::BoardInvalid(format!(
                        "{what}: expected its grid read from the file (load the board with its files, e.g. `hbmu fe --board FILE`), found none"
                    )));
                };
                if g.nx == 0 || g.ny == 0 || g.values.len() != g.nx * g.ny {
                    return Err(FemError::BoardInvalid(format!(
                        "{what}: expected a non-empty {} × {} grid, found {} values",
                        g.nx,
                        g.ny,
                        g.values.len()
                    )));
                }
                if let Some(v) = g.values.iter().find(|v| !(0.0..=1.0).contains(*v)) {
                    return Err(FemError::BoardInvalid(format!(
                        "{what}: expected fractions in [0, 1], found {v}"
                    )));
                }
            }
            if let (Some(f), None) = (&l.gerber, &l.gerber_image) {
                return Err(FemError::BoardInvalid(format!(
                    "copper[{i}].gerber ({f}): expected its image read from the file (load the board with its files, e.g. `hbmu fe --board FILE`), found none"
                )));
            }
            if !(l.nu > -1.0 && l.nu < 0.5) {
                return Err(FemError::BoardInvalid(format!(
                    "copper[{i}].nu: expected -1 < ν < 0.5, found {}",
                    l.nu
                )));
            }
        }
        for (i, h) in self.holes.iter().enumerate() {
            pos(&format!("holes[{i}].diameter_m"), h.diameter_m)?;
            if !(h.x_m > 0.0 && h.x_m < self.length_x_m && h.y_m > 0.0 && h.y_m < self.width_y_m) {
                return Err(FemError::BoardInvalid(format!(
                    "holes[{i}]: expected centre inside the {} × {} m outline, found ({}, {})",
                    self.length_x_m, self.width_y_m, h.x_m, h.y_m
                )));
            }
        }
        for (i, h) in self.holes.iter().enumerate() {
            for (j, g) in self.holes.iter().enumerate().skip(i + 1) {
                if (h.x_m - g.x_m).hypot(h.y_m - g.y_m) < 0.5 * (h.diameter_m + g.diameter_m) {
                    return Err(FemError::BoardInvalid(format!(
                        "holes[{i}] and holes[{j}]: expected disjoint holes, found overlapping discs"
                    )));
                }
            }
        }
        if let Some(g) = &self.gerber {
            pos("gerber.resolution_m", g.resolution_m)?;
        }
        match &self.joint {
            None if !self.holes.is_empty() => {
                return Err(FemError::BoardInvalid(format!(
                    "{} holes but no [joint] section: expected the bolted joints' clamp_diameter_m, k_con_n_per_m and bolt_mass_kg",
                    self.holes.len()
                )))
            }
            None => {}
            Some(joint) => {
                pos("joint.clamp_diameter_m", joint.clamp_diameter_m)?;
                pos("joint.k_con_n_per_m", joint.k_con_n_per_m)?;
                for (what, v) in [
                    ("bolt_mass_kg", joint.bolt_mass_kg),
                    ("tangential_over_normal", joint.tangential_over_normal),
                ] {
                    if !(v >= 0.0 && v.is_finite()) {
                        return Err(FemError::BoardInvalid(format!(
                            "joint.{what}: expected a finite value >= 0, found {v}"
                        )));
                    }
                }
            }
        }
        for (what, m) in [
            ("mesh", Some(&self.mesh)),
            ("mesh_bolted", self.mesh_bolted.as_ref()),
        ] {
            if let Some(m) = m.filter(|m| m.nx == 0 || m.ny == 0) {
                return Err(FemError::BoardInvalid(format!(
                    "{what}: expected nx, ny >= 1, found {} × {}",
                    m.nx, m.ny
                )));
            }
        }
        if self.scan_grid.nx == 0 || self.scan_grid.ny == 0 {
            return Err(FemError::BoardInvalid(format!(
                "scan_grid: expected nx, ny >= 1, found {} × {}",
                self.scan_grid.nx, self.scan_grid.ny
            )));
        }
        Ok(())
    }

    /// Points of the default scan grid, `[x_m, y_m]`, x fastest.
    pub fn scan_points_m(&self) -> Vec<[f64; 2]> {
        let g = &self.scan_grid;
        let coord = |n: usize, len: f64, i: usize| {
            if n == 1 {
                0.5 * len
            } else {
                g.margin_m + (len - 2.0 * g.margin_m) * i as f64 / (n - 1) as f64
            }
        };
        let mut pts = Vec::with_capacity(g.nx * g.ny);
        for j in 0..g.ny {
            for i in 0..g.nx {
                pts.push([
                    coord(g.nx, self.length_x_m, i),
                    coord(g.ny, self.width_y_m, j),
                ]);
            }
        }
        pts
    }

    /// Fraction of copper layer `layer` covering the rectangle `[x0,x1]×[y0,y1]`:
    /// the exact area-weighted mean of the pointwise coverage (regions take the
    /// maximum where they overlap, cut-outs subtract the maximum of theirs, capped to
    /// [0, 1]; see [`super::copper`]).
    pub fn coverage_fraction(&self, layer: usize, x0: f64, y0: f64, x1: f64, y1: f64) -> f64 {
        super::copper::CopperMap::new(self).mean_coverage(layer, &Rect { x0, y0, x1, y1 })
    }
}
