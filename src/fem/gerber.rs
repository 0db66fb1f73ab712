//! Gerber RS-274X images to raster copper coverage: pure functions over parsed statements
//! (`formats::gerber` reads the files).
//!
//! [`render`] executes the statements (apertures C/R/O/P with holes, D01 strokes with
//! circular or rectangular apertures, D03 flashes, G36/G37 regions, G01/G02/G03 with
//! G74/G75, LP polarity, LM/LR/LS aperture transforms, SR step-and-repeat) into an
//! ordered list of polygonal features, each dark or clear. Arcs and circles are
//! flattened to a chord sagitta of at most [`FLATTEN_TOL_M`], circles with a radius
//! scaled so each polygon keeps the disc's exact area.
//!
//! [`rasterize`] turns the features into the coverage fraction of each cell of a grid:
//! every cell is cut into [`SUB_ROWS`] horizontal sub-rows; on the mid-line of each, the
//! image is an exact set of x-intervals (dark features add their intervals in file order,
//! clear ones remove theirs, as the Gerber image model prescribes), whose length inside
//! each cell is accumulated exactly. The coverage is thus exact along x and midpoint-rule
//! integrated along y, the sub-rows being cut at every horizontal edge (so axis-aligned
//! shapes are exact; a sloped edge errs only where a vertex or a cell edge falls inside a
//! sub-row, second order in the sub-row height).

use super::board::Grid;
use super::geometry::Rect;

/// Largest chord sagitta of flattened arcs and circles, m.
pub const FLATTEN_TOL_M: f64 = 1e-7;
/// Sub-rows per raster cell in [`rasterize`].
pub const SUB_ROWS: usize = 8;

/// Where a statement came from: its 1-based line and its text, for error messages.
#[derive(Clone, Debug, PartialEq)]
pub struct SrcPos {
    /// 1-based line of the file where the command starts.
    pub line: usize,
    /// The command's text (one word, or one extended-command word without `%`).
    pub command: String,
}

/// An aperture template of the standard set (sizes in m).
#[derive(Clone, Debug, PartialEq)]
pub enum ApertureShape {
    /// Circle of diameter `d_m`.
    Circle {
        /// Diameter, m.
        d_m: f64,
        /// Optional round hole, diameter m.
        hole_m: Option<f64>,
    },
    /// Rectangle `w_m × h_m` centred on the flash point.
    Rect {
        /// Width along x, m.
        w_m: f64,
        /// Height along y, m.
        h_m: f64,
        /// Optional round hole, diameter m.
        hole_m: Option<f64>,
    },
    /// Obround (stadium) `w_m × h_m`.
    Obround {
        /// Width along x, m.
        w_m: f64,
        /// Height along y, m.
        h_m: f64,
        /// Optional round hole, diameter m.
        hole_m: Option<f64>,
    },
    /// Regular polygon of `n` vertices on a circle of diameter `d_m`, the first vertex
    /// at `rotation_deg` counter-clockwise from +x.
    Polygon {
        /// Outer diameter, m.
        d_m: f64,
        /// Number of vertices, 3..=12.
        n: u32,
        /// Rotation, degrees.
        rotation_deg: f64,
        /// Optional round hole, diameter m.
        hole_m: Option<f64>,
    },
    /// An aperture macro instance, evaluated ([`macro_primitive`]).
    Macro {
        /// The macro's name.
        name: String,
        /// Its primitives in order.
        primitives: Vec<MacroPrimitive>,
    },
}

/// One primitive of an evaluated aperture macro (`%AM…%` instantiated by `%AD…%`): its
/// contours (even–odd) in the macro's frame, m, and its exposure. Exposure off erases
/// what the macro's earlier primitives drew, within the aperture only.
#[derive(Clone, Debug, PartialEq)]
pub struct MacroPrimitive {
    /// Exposure on (adds to the aperture) or off (erases from it).
    pub exposure: bool,
    /// Closed contours, m.
    pub contours: Vec<Vec<[f64; 2]>>,
}

/// Interpolation mode (G01/G02/G03).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interp {
    /// G01.
    Linear,
    /// G02.
    Clockwise,
    /// G03.
    CounterClockwise,
}

/// One executable Gerber statement, coordinates already in metres.
#[derive(Clone, Debug, PartialEq)]
pub enum Cmd {
    /// `%ADDnn…%`.
    ApertureDef {
        /// D-code (≥ 10).
        code: u32,
        /// Template.
        shape: ApertureShape,
    },
    /// `Dnn` (nn ≥ 10).
    Select(u32),
    /// G01/G02/G03.
    Interp(Interp),
    /// G74 (false) / G75 (true).
    Quadrant {
        /// Multi-quadrant (G75).
        multi: bool,
    },
    /// G36 (true) / G37 (false).
    Region(bool),
    /// `%LPD%` (true) / `%LPC%` (false).
    Polarity {
        /// Dark.
        dark: bool,
    },
    /// `%LM…%`.
    Mirror {
        /// Mirror x coordinates (about the y axis).
        x: bool,
        /// Mirror y coordinates.
        y: bool,
    },
    /// `%LR…%`, degrees counter-clockwise.
    Rotate(f64),
    /// `%LS…%`.
    Scale(f64),
    /// `%SRX…Y…I…J…%`: open a step-and-repeat block.
    StepRepeat {
        /// Copies along x.
        nx: u32,
        /// Copies along y.
        ny: u32,
        /// Step along x, m.
        dx_m: f64,
        /// Step along y, m.
        dy_m: f64,
    },
    /// `%SR%`: close the block.
    StepRepeatEnd,
    /// D01 (1), D02 (2) or D03 (3) with optional coordinates, m.
    Op {
        /// 1, 2 or 3.
        d: u8,
        /// X, m.
        x: Option<f64>,
        /// Y, m.
        y: Option<f64>,
        /// I (arc centre offset), m.
        i: Option<f64>,
        /// J, m.
        j: Option<f64>,
    },
    /// M02.
    End,
}

/// A statement with its source position.
#[derive(Clone, Debug, PartialEq)]
pub struct Stmt {
    /// Where it came from.
    pub pos: SrcPos,
    /// What it does.
    pub cmd: Cmd,
}

/// An error executing a statement: names its line and command.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("line {}: `{}`: {message}", pos.line, pos.command)]
pub struct GerberError {
    /// The offending statement's position.
    pub pos: SrcPos,
    /// What was expected and what was found.
    pub message: String,
}

/// A filled shape of the image: contours combined by the even–odd rule, dark or clear.
#[derive(Clone, Debug, PartialEq)]
pub struct Feature {
    /// Dark (adds copper) or clear (removes it).
    pub dark: bool,
    /// Closed contours (last vertex joins the first), m.
    pub contours: Vec<Vec<[f64; 2]>>,
    /// Empty: all contours form one even–odd shape. Otherwise (a macro flash) the
    /// contours in consecutive groups `(count, exposure)`, combined in order: a group
    /// with exposure on adds its shape, one with exposure off erases it, within the
    /// feature only.
    pub parts: Vec<(usize, bool)>,
    /// Bounding box.
    pub bbox: Rect,
}

/// A rendered Gerber image.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Image {
    /// Features in drawing order.
    pub features: Vec<Feature>,
    /// Bounding box of the drawn centre-lines (D01 paths and region contours), the
    /// board edge when the file is a profile (outline) layer; `None` if nothing drawn.
    pub path_bbox: Option<Rect>,
}

impl Image {
    /// Shift every feature (and the path box) by (dx, dy), m.
    pub fn translate(&mut self, dx: f64, dy: f64) {
        let sh = |r: &mut Rect| {
            r.x0 += dx;
            r.x1 += dx;
            r.y0 += dy;
            r.y1 += dy;
        };
        for f in &mut self.features {
            for p in f.contours.iter_mut().flatten() {
                p[0] += dx;
                p[1] += dy;
            }
            sh(&mut f.bbox);
        }
        if let Some(b) = &mut self.path_bbox {
            sh(b);
        }
    }
}

fn bbox_of(contours: &[Vec<[f64; 2]>]) -> Rect {
    let mut r = Rect {
        x0: f64::INFINITY,
        y0: f64::INFINITY,
        x1: f64::NEG_INFINITY,
        y1: f64::NEG_INFINITY,
    };
    for p in contours.iter().flatten() {
        r.x0 = r.x0.min(p[0]);
        r.y0 = r.y0.min(p[1]);
        r.x1 = r.x1.max(p[0]);
        r.y1 = r.y1.max(p[1]);
    }
    r
}

fn grow(b: &mut Option<Rect>, p: [f64; 2]) {
    let r = b.get_or_insert(Rect {
        x0: p[0],
        y0: p[1],
        x1: p[0],
        y1: p[1],
    });
    r.x0 = r.x0.min(p[0]);
    r.y0 = r.y0.min(p[1]);
    r.x1 = r.x1.max(p[0]);
    r.y1 = r.y1.max(p[1]);
}

/// Segments needed for an arc of radius `r` and sweep `sweep` (rad) at sagitta ≤ tol.
fn arc_segments(r: f64, sweep: f64) -> usize {
    if r <= FLATTEN_TOL_M {
        return 4;
    }
    let step = 2.0 * (1.0 - FLATTEN_TOL_M / r).clamp(-1.0, 1.0).acos();
    ((sweep.abs() / step).ceil() as usize).clamp(4, 4096)
}

/// A counter-clockwise polygon of the disc (cx, cy, r) with the disc's exact area.
pub fn disc(c: [f64; 2], r: f64) -> Vec<[f64; 2]> {
    let n = arc_segments(r, 2.0 * std::f64::consts::PI).max(16);
    let t = 2.0 * std::f64::consts::PI / n as f64;
    // Area of the regular n-gon of circumradius ρ: n ρ² sin(t) / 2 = π r².
    let rho = r * (2.0 * std::f64::consts::PI / (n as f64 * t.sin())).sqrt();
    (0..n)
        .map(|k| {
            let a = k as f64 * t;
            [c[0] + rho * a.cos(), c[1] + rho * a.sin()]
        })
        .collect()
}

/// The area swept by a disc of radius `r` moving from `p` to `q` (a convex capsule).
pub fn capsule(p: [f64; 2], q: [f64; 2], r: f64) -> Vec<[f64; 2]> {
    let (dx, dy) = (q[0] - p[0], q[1] - p[1]);
    if dx.hypot(dy) <= 1e-15 {
        return disc(p, r);
    }
    let th = dy.atan2(dx);
    let n = arc_segments(r, std::f64::consts::PI).max(8);
    // Each end is a fan of n triangles over a half disc: its two end vertices stay at r
    // (so the straight sides are exactly 2r apart), the n − 1 inner ones at ρ chosen so
    // the fan has the half disc's area: ½ sin t [2 r ρ + (n − 2) ρ²] = π r² / 2.
    let t = std::f64::consts::PI / n as f64;
    let m = (n - 2) as f64;
    let rho = r * (-1.0 + (1.0 + m * std::f64::consts::PI / t.sin()).sqrt()) / m;
    let mut out = Vec::with_capacity(2 * n + 2);
    let rad = |k: usize| if k == 0 || k == n { r } else { rho };
    for k in 0..=n {
        let a = th - std::f64::consts::FRAC_PI_2 + k as f64 * t;
        out.push([q[0] + rad(k) * a.cos(), q[1] + rad(k) * a.sin()]);
    }
    for k in 0..=n {
        let a = th + std::f64::consts::FRAC_PI_2 + k as f64 * t;
        out.push([p[0] + rad(k) * a.cos(), p[1] + rad(k) * a.sin()]);
    }
    out
}

/// Convex hull (Andrew's monotone chain), counter-clockwise.
fn convex_hull(mut pts: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    pts.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let mut lower: Vec<[f64; 2]> = Vec::new();
    for &p in &pts {
        while lower.len() >= 2 && cross(lower[lower.len() - 2], lower[lower.len() - 1], p) <= 0.0 {
            lower.pop();
        }
        lower.push(p);
    }
    let mut upper: Vec<[f64; 2]> = Vec::new();
    for &p in pts.iter().rev() {
        while upper.len() >= 2 && cross(upper[upper.len() - 2], upper[upper.len() - 1], p) <= 0.0 {
            upper.pop();
        }
        upper.push(p);
    }
    lower.pop();
    upper.pop();
    lower.extend(upper);
    lower
}

/// Aperture transform (LM, LR, LS), applied mirror → rotate → scale.
#[derive(Clone, Copy, Debug)]
struct Xform {
    mx: bool,
    my: bool,
    rot_deg: f64,
    scale: f64,
}

impl Xform {
    fn apply(&self, p: [f64; 2]) -> [f64; 2] {
        let (mut x, mut y) = (p[0], p[1]);
        if self.mx {
            x = -x;
        }
        if self.my {
            y = -y;
        }
        let (s, c) = self.rot_deg.to_radians().sin_cos();
        [self.scale * (c * x - s * y), self.scale * (s * x + c * y)]
    }
}

/// Contours of an aperture flashed at the origin (outline, then an optional hole).
fn aperture_contours(a: &ApertureShape, xf: &Xform) -> Vec<Vec<[f64; 2]>> {
    let (outline, hole) = match a {
        ApertureShape::Circle { d_m, hole_m } => (disc([0.0, 0.0], 0.5 * d_m), hole_m),
        ApertureShape::Rect { w_m, h_m, hole_m } => {
            let (w, h) = (0.5 * w_m, 0.5 * h_m);
            (vec![[-w, -h], [w, -h], [w, h], [-w, h]], hole_m)
        }
        ApertureShape::Obround { w_m, h_m, hole_m } => {
            let r = 0.5 * w_m.min(*h_m);
            let (hx, hy) = (0.5 * w_m - r, 0.5 * h_m - r);
            (capsule([-hx, -hy], [hx, hy], r), hole_m)
        }
        ApertureShape::Polygon {
            d_m,
            n,
            rotation_deg,
            hole_m,
        } => {
            let r = 0.5 * d_m;
            let pts = (0..*n)
                .map(|k| {
                    let a = rotation_deg.to_radians()
                        + 2.0 * std::f64::consts::PI * k as f64 / *n as f64;
                    [r * a.cos(), r * a.sin()]
                })
                .collect();
            (pts, hole_m)
        }
        ApertureShape::Macro { primitives, .. } => {
            return primitives
                .iter()
                .flat_map(|p| p.contours.iter())
                .map(|c| c.iter().map(|p| xf.apply(*p)).collect())
                .collect();
        }
    };
    let mut out = vec![outline];
    if let Some(h) = hole {
        if *h > 0.0 {
            out.push(disc([0.0, 0.0], 0.5 * h));
        }
    }
    out.into_iter()
        .map(|c| c.into_iter().map(|p| xf.apply(p)).collect())
        .collect()
}

/// Points of the arc from `p` to `q` about `c` (excluding `p`, including `q`);
/// `cw` for clockwise. A full circle when `p == q`.
fn arc_points(p: [f64; 2], q: [f64; 2], c: [f64; 2], cw: bool) -> Vec<[f64; 2]> {
    let r = (p[0] - c[0]).hypot(p[1] - c[1]);
    let a0 = (p[1] - c[1]).atan2(p[0] - c[0]);
    let a1 = (q[1] - c[1]).atan2(q[0] - c[0]);
    let tau = 2.0 * std::f64::consts::PI;
    let mut sweep = if cw { a0 - a1 } else { a1 - a0 };
    sweep = sweep.rem_euclid(tau);
    if sweep <= 1e-12 {
        sweep = tau;
    }
    let n = arc_segments(r, sweep);
    let r1 = (q[0] - c[0]).hypot(q[1] - c[1]);
    (1..=n)
        .map(|k| {
            if k == n {
                return q;
            }
            let f = k as f64 / n as f64;
            let a = if cw { a0 - f * sweep } else { a0 + f * sweep };
            // Radius interpolated between the (nearly equal) end radii.
            let rr = r + f * (r1 - r);
            [c[0] + rr * a.cos(), c[1] + rr * a.sin()]
        })
        .collect()
}

/// Rotate `p` by `deg` degrees counter-clockwise about the origin.
fn rot(p: [f64; 2], deg: f64) -> [f64; 2] {
    let (s, c) = deg.to_radians().sin_cos();
    [c * p[0] - s * p[1], s * p[0] + c * p[1]]
}

/// The part of the annulus `r_in ≤ |p| ≤ r_out` in the first quadrant beyond the two
/// gap strips |x| < g, |y| < g (one quarter of a thermal primitive), counter-clockwise.
fn thermal_quarter(r_out: f64, r_in: f64, g: f64) -> Vec<[f64; 2]> {
    let a0 = (g / r_out).asin();
    let sweep = std::f64::consts::FRAC_PI_2 - 2.0 * a0;
    let n = arc_segments(r_out, sweep);
    let mut out: Vec<[f64; 2]> = (0..=n)
        .map(|k| {
            let a = a0 + sweep * k as f64 / n as f64;
            [r_out * a.cos(), r_out * a.sin()]
        })
        .collect();
    if r_in > g {
        let b0 = (g / r_in).asin();
        let sw = std::f64::consts::FRAC_PI_2 - 2.0 * b0;
        let m = arc_segments(r_in, sw);
        out.extend((0..=m).map(|k| {
            let a = std::f64::consts::FRAC_PI_2 - b0 - sw * k as f64 / m as f64;
            [r_in * a.cos(), r_in * a.sin()]
        }));
    } else {
        out.push([g, g]);
    }
    out
}

/// Evaluate one aperture-macro primitive of the standard set (Gerber 2021 §4.5.1):
/// `code` and its parameters `p` as written (file units; `unit_m` metres per unit,
/// angles in degrees), to its contours in the macro frame, m. `None` for a comment
/// (code 0). The error says what was expected.
///
/// 1 circle (exposure, diameter, centre x, y[, rotation]); 20 vector line (exposure,
/// width, start x, y, end x, y, rotation); 21 centre line (exposure, width, height,
/// centre x, y, rotation); 4 outline (exposure, n, n + 1 points with the last equal to
/// the first, rotation); 5 polygon (exposure, n = 3…12, centre x, y, diameter,
/// rotation); 7 thermal (centre x, y, outer and inner diameters, gap, rotation; always
/// exposed). Rotations turn the primitive about the macro origin.
pub fn macro_primitive(
    code: u32,
    p: &[f64],
    unit_m: f64,
) -> Result<Option<MacroPrimitive>, String> {
    let need = |lo: usize, hi: usize, what: &str| -> Result<(), String> {
        if p.len() < lo || p.len() > hi {
            Err(format!(
                "expected {} parameters for primitive {code} ({what}), found {}",
                if lo == hi {
                    lo.to_string()
                } else {
                    format!("{lo} to {hi}")
                },
                p.len()
            ))
        } else {
            Ok(())
        }
    };
    let exposure = |v: f64| -> Result<bool, String> {
        if v == 1.0 {
            Ok(true)
        } else if v == 0.0 {
            Ok(false)
        } else {
            Err(format!("expected exposure 0 (off) or 1 (on), found {v}"))
        }
    };
    let u = unit_m;
    let finish = |on: bool, contours: Vec<Vec<[f64; 2]>>, deg: f64| {
        Some(MacroPrimitive {
            exposure: on,
            contours: contours
                .into_iter()
                .map(|c| c.into_iter().map(|q| rot(q, deg)).collect())
                .collect(),
        })
    };
    match code {
        0 => Ok(None),
        1 => {
            need(4, 5, "circle: exposure, diameter, centre x, y[, rotation]")?;
            if !(p[1] >= 0.0) {
                return Err(format!("expected a non-negative circle diameter, found {}", p[1]));
            }
            let c = disc([p[2] * u, p[3] * u], 0.5 * p[1] * u);
            Ok(finish(exposure(p[0])?, vec![c], p.get(4).copied().unwrap_or(0.0)))
        }
        20 => {
            need(7, 7, "vector line: exposure, width, start x, y, end x, y, rotation")?;
            let (w, s, e) = (p[1] * u, [p[2] * u, p[3] * u], [p[4] * u, p[5] * u]);
            if !(w >= 0.0) {
                return Err(format!("expected a non-negative line width, found {}", p[1]));
            }
            let len = (e[0] - s[0]).hypot(e[1] - s[1]);
            let c = if len > 0.0 && w > 0.0 {
                let n = [-(e[1] - s[1]) / len * 0.5 * w, (e[0] - s[0]) / len * 0.5 * w];
                vec![vec![
                    [s[0] - n[0], s[1] - n[1]],
                    [e[0] - n[0], e[1] - n[1]],
                    [e[0] + n[0], e[1] + n[1]],
                    [s[0] + n[0], s[1] + n[1]],
                ]]
            } else {
                Vec::new()
            };
            Ok(finish(exposure(p[0])?, c, p[6]))
        }
        21 => {
            need(6, 6, "centre line: exposure, width, height, centre x, y, rotation")?;
            let (w, h, cx, cy) = (0.5 * p[1] * u, 0.5 * p[2] * u, p[3] * u, p[4] * u);
            if !(w >= 0.0 && h >= 0.0) {
                return Err(format!(
                    "expected a non-negative width and height, found {} and {}",
                    p[1], p[2]
                ));
            }
            let c = vec![vec![
                [cx - w, cy - h],
                [cx + w, cy - h],
                [cx + w, cy + h],
                [cx - w, cy + h],
            ]];
            Ok(finish(exposure(p[0])?, c, p[5]))
        }
        4 => {
            if p.len() < 2 {
                return Err(format!(
                    "expected exposure and vertex count for primitive 4 (outline), found {} parameters",
                    p.len()
                ));
            }
            let n = p[1];
            if !(n >= 3.0 && n.fract() == 0.0) {
                return Err(format!("expected a whole vertex count ≥ 3 for the outline, found {n}"));
            }
            let n = n as usize;
            need(2 * n + 5, 2 * n + 5, "outline: exposure, n, n + 1 points, rotation")?;
            let pts: Vec<[f64; 2]> = (0..=n).map(|k| [p[2 + 2 * k] * u, p[3 + 2 * k] * u]).collect();
            let (a, b) = (pts[0], pts[n]);
            if (a[0] - b[0]).hypot(a[1] - b[1]) > 1e-9 {
                return Err(format!(
                    "expected the outline's last point equal to its first, found ({}, {}) and ({}, {})",
                    p[2], p[3], p[2 + 2 * n], p[3 + 2 * n]
                ));
            }
            Ok(finish(exposure(p[0])?, vec![pts[..n].to_vec()], p[2 * n + 4]))
        }
        5 => {
            need(6, 6, "polygon: exposure, n, centre x, y, diameter, rotation")?;
            let n = p[1];
            if !((3.0..=12.0).contains(&n) && n.fract() == 0.0) {
                return Err(format!("expected 3 to 12 polygon vertices, found {n}"));
            }
            if !(p[4] >= 0.0) {
                return Err(format!("expected a non-negative polygon diameter, found {}", p[4]));
            }
            let (c, r) = ([p[2] * u, p[3] * u], 0.5 * p[4] * u);
            let pts = (0..n as usize)
                .map(|k| {
                    let a = 2.0 * std::f64::consts::PI * k as f64 / n;
                    [c[0] + r * a.cos(), c[1] + r * a.sin()]
                })
                .collect();
            Ok(finish(exposure(p[0])?, vec![pts], p[5]))
        }
        7 => {
            need(6, 6, "thermal: centre x, y, outer diameter, inner diameter, gap, rotation")?;
            let (c, ro, ri, g) = ([p[0] * u, p[1] * u], 0.5 * p[2] * u, 0.5 * p[3] * u, 0.5 * p[4] * u);
            if !(ri >= 0.0 && ro > ri && g >= 0.0 && g * std::f64::consts::SQRT_2 < ro) {
                return Err(format!(
                    "expected outer diameter > inner diameter ≥ 0 and 0 ≤ gap < outer diameter / √2, found {}, {}, {}",
                    p[2], p[3], p[4]
                ));
            }
            let q = thermal_quarter(ro, ri, g);
            let contours = (0..4)
                .map(|k| {
                    q.iter()
                        .map(|&v| {
                            let w = rot(v, 90.0 * k as f64);
                            [w[0] + c[0], w[1] + c[1]]
                        })
                        .collect()
                })
                .collect();
            Ok(finish(true, contours, p[5]))
        }
        _ => Err(format!(
            "expected a macro primitive code 0 (comment), 1 (circle), 20 (vector line), 21 (centre line), 4 (outline), 5 (polygon) or 7 (thermal), found {code}"
        )),
    }
}

/// A Gerber error at statement `s`.
fn err(s: &Stmt, m: String) -> GerberError {
    GerberError {
        pos: s.pos.clone(),
        message: m,
    }
}

fn push(img: &mut Image, dark: bool, contours: Vec<Vec<[f64; 2]>>) {
    push_parts(img, dark, contours, Vec::new());
}

fn push_parts(
    img: &mut Image,
    dark: bool,
    contours: Vec<Vec<[f64; 2]>>,
    parts: Vec<(usize, bool)>,
) {
    let bbox = bbox_of(&contours);
    img.features.push(Feature {
        dark,
        contours,
        parts,
        bbox,
    });
}

/// Checks the aperture definition `code` = `shape` at `s`.
fn check_aperture(s: &Stmt, code: u32, shape: &ApertureShape) -> Result<(), GerberError> {
    let code = &code;
    if *code < 10 {
        return Err(err(
            s,
            format!("expected an aperture number ≥ 10, found {code}"),
        ));
    }
    let bad = match shape {
        ApertureShape::Circle { d_m, hole_m } => {
            !(*d_m >= 0.0) || hole_m.is_some_and(|h| !(h >= 0.0 && h < *d_m))
        }
        ApertureShape::Rect { w_m, h_m, hole_m } | ApertureShape::Obround { w_m, h_m, hole_m } => {
            !(*w_m > 0.0 && *h_m > 0.0) || hole_m.is_some_and(|h| !(h >= 0.0 && h < w_m.min(*h_m)))
        }
        ApertureShape::Polygon { d_m, n, hole_m, .. } => {
            !(*d_m > 0.0 && (3..=12).contains(n)) || hole_m.is_some_and(|h| !(h >= 0.0 && h < *d_m))
        }
        ApertureShape::Macro { primitives, .. } => primitives
            .iter()
            .flat_map(|p| p.contours.iter().flatten())
            .any(|v| !(v[0].is_finite() && v[1].is_finite())),
    };
    if bad {
        return Err(err(
            s,
            format!("expected positive aperture sizes (polygon: 3 to 12 vertices) with a hole inside the aperture, found {shape:?}"),
        ));
    }
    Ok(())
}

/// The graphics state while executing Gerber statements, and the image drawn so far.
struct Renderer {
    apertures: std::collections::HashMap<u32, ApertureShape>,
    current: Option<u32>,
    interp: Interp,
    multi: bool,
    dark: bool,
    xf: Xform,
    pt: Option<[f64; 2]>,
    img: Image,
    region: Option<Vec<Vec<[f64; 2]>>>,
    contour: Vec<[f64; 2]>,
    sr: Option<(usize, u32, u32, f64, f64)>,
    ended: bool,
}

/// Execute Gerber statements into an image.
pub fn render(stmts: &[Stmt]) -> Result<Image, GerberError> {
    let mut r = Renderer {
        apertures: std::collections::HashMap::new(),
        current: None,
        // The 2021 specification asks for G01/G02/G03 before the first D01; older files (and
        // writers such as gerbonara 1.5) rely on the former default, linear.
        interp: Interp::Linear,
        multi: true,
        dark: true,
        xf: Xform {
            mx: false,
            my: false,
            rot_deg: 0.0,
            scale: 1.0,
        },
        pt: None,
        img: Image::default(),
        region: None,
        contour: Vec::new(),
        sr: None,
        ended: false,
    };
    for s in stmts {
        r.step(s)?;
    }
    if r.region.is_some() {
        let s = stmts.last().map(|s| s.pos.clone()).unwrap_or(SrcPos {
            line: 0,
            command: String::new(),
        });
        return Err(GerberError {
            pos: s,
            message: "expected G37 to close the region, found the end of the file".into(),
        });
    }
    r.close_sr();
    Ok(r.img)
}

impl Renderer {
    /// Close the current region contour (if any segment was drawn) into a feature.
    fn close_contour(&mut self, s: &Stmt) -> Result<(), GerberError> {
        if self.contour.len() > 1 {
            let (a, b) = (self.contour[0], self.contour[self.contour.len() - 1]);
            if (a[0] - b[0]).hypot(a[1] - b[1]) > 1e-6 {
                return Err(err(
                s,
                format!(
                    "expected the region contour started at ({:.6}, {:.6}) mm to be closed, found it ending at ({:.6}, {:.6}) mm",
                    a[0] * 1e3,
                    a[1] * 1e3,
                    b[0] * 1e3,
                    b[1] * 1e3
                ),
            ));
            }
            push(
                &mut self.img,
                self.dark,
                vec![std::mem::take(&mut self.contour)],
            );
        }
        self.contour.clear();
        Ok(())
    }

    /// Close the current step-and-repeat block: its copies.
    fn close_sr(&mut self) {
        if let Some((start, nx, ny, dx, dy)) = self.sr.take() {
            let block: Vec<Feature> = self.img.features[start..].to_vec();
            for j in 0..ny {
                for i in 0..nx {
                    if i == 0 && j == 0 {
                        continue;
                    }
                    let (ox, oy) = (i as f64 * dx, j as f64 * dy);
                    for f in &block {
                        let contours: Vec<Vec<[f64; 2]>> = f
                            .contours
                            .iter()
                            .map(|c| c.iter().map(|p| [p[0] + ox, p[1] + oy]).collect())
                            .collect();
                        push_parts(&mut self.img, f.dark, contours, f.parts.clone());
                    }
                }
            }
        }
    }

    /// Execute statement `s`.
    fn step(&mut self, s: &Stmt) -> Result<(), GerberError> {
        if self.ended {
            return Err(err(s, "expected nothing after M02 (end of file)".into()));
        }
        match &s.cmd {
            Cmd::ApertureDef { code, shape } => {
                check_aperture(s, *code, shape)?;
                self.apertures.insert(*code, shape.clone());
            }
            Cmd::Select(code) => {
                if self.region.is_some() {
                    return Err(err(
                        s,
                        "expected no aperture selection inside a region statement (G36 … G37)"
                            .into(),
                    ));
                }
                if !self.apertures.contains_key(code) {
                    return Err(err(
                        s,
                        format!("expected a defined aperture, found D{code} undefined (no %ADD{code}…% before this line)"),
                    ));
                }
                self.current = Some(*code);
            }
            Cmd::Interp(m) => self.interp = *m,
            Cmd::Quadrant { multi: m } => self.multi = *m,
            Cmd::Region(on) => {
                if *on {
                    if self.region.is_some() {
                        return Err(err(
                            s,
                            "expected G37 before another G36, found a nested G36".into(),
                        ));
                    }
                    self.region = Some(Vec::new());
                    self.contour.clear();
                } else {
                    if self.region.is_none() {
                        return Err(err(
                            s,
                            "expected G36 before G37, found G37 outside a region".into(),
                        ));
                    }
                    self.close_contour(s)?;
                    self.region = None;
                }
            }
            Cmd::Polarity { dark: d } => {
                if self.region.is_some() {
                    return Err(err(
                        s,
                        "expected no polarity change inside a region statement".into(),
                    ));
                }
                self.dark = *d;
            }
            Cmd::Mirror { x, y } => {
                self.xf.mx = *x;
                self.xf.my = *y;
            }
            Cmd::Rotate(a) => self.xf.rot_deg = *a,
            Cmd::Scale(f) => {
                if !(*f > 0.0) {
                    return Err(err(s, format!("expected a positive scale, found {f}")));
                }
                self.xf.scale = *f;
            }
            Cmd::StepRepeat { nx, ny, dx_m, dy_m } => {
                self.close_sr();
                if *nx == 0 || *ny == 0 {
                    return Err(err(
                        s,
                        format!("expected at least one copy along x and y, found {nx} × {ny}"),
                    ));
                }
                self.sr = Some((self.img.features.len(), *nx, *ny, *dx_m, *dy_m));
            }
            Cmd::StepRepeatEnd => self.close_sr(),
            Cmd::End => {
                if self.region.is_some() {
                    return Err(err(s, "expected G37 to close the region before M02".into()));
                }
                self.close_sr();
                self.ended = true;
            }
            Cmd::Op { d, x, y, i, j } => self.op(s, *d, *x, *y, *i, *j)?,
        }
        Ok(())
    }

    /// An operation: D01 (draw), D02 (move) or D03 (flash) to (x, y).
    fn op(
        &mut self,
        s: &Stmt,
        d: u8,
        x: Option<f64>,
        y: Option<f64>,
        i: Option<f64>,
        j: Option<f64>,
    ) -> Result<(), GerberError> {
        let (x, y) = (&x, &y);
        let from = self.pt;
        let to = match (x, y, from) {
            (Some(x), Some(y), _) => [*x, *y],
            (Some(x), None, Some(p)) => [*x, p[1]],
            (None, Some(y), Some(p)) => [p[0], *y],
            (None, None, Some(p)) => p,
            _ => {
                return Err(err(
                    s,
                    "expected both X and Y: the current point is undefined before the first full coordinate".into(),
                ))
            }
        };
        match d {
            2 => {
                if self.region.is_some() {
                    self.close_contour(s)?;
                }
                self.pt = Some(to);
            }
            3 => {
                if self.region.is_some() {
                    return Err(err(
                        s,
                        "expected no flash (D03) inside a region statement".into(),
                    ));
                }
                let Some(code) = self.current else {
                    return Err(err(
                        s,
                        "expected an aperture selected (Dnn) before a flash, found none".into(),
                    ));
                };
                let ap = &self.apertures[&code];
                let c = aperture_contours(ap, &self.xf)
                    .into_iter()
                    .map(|c| {
                        c.into_iter()
                            .map(|p| [p[0] + to[0], p[1] + to[1]])
                            .collect()
                    })
                    .collect();
                let parts = match ap {
                    ApertureShape::Macro { primitives, .. } => primitives
                        .iter()
                        .map(|p| (p.contours.len(), p.exposure))
                        .collect(),
                    _ => Vec::new(),
                };
                push_parts(&mut self.img, self.dark, c, parts);
                self.pt = Some(to);
            }
            1 => self.draw(s, from, to, i, j)?,
            _ => return Err(err(s, format!("expected D01, D02 or D03, found D{d:02}"))),
        }
        Ok(())
    }

    /// A draw (D01) from `from` to `to` with the arc centre offsets `i`, `j`.
    fn draw(
        &mut self,
        s: &Stmt,
        from: Option<[f64; 2]>,
        to: [f64; 2],
        i: Option<f64>,
        j: Option<f64>,
    ) -> Result<(), GerberError> {
        let mode = self.interp;
        let Some(p) = from else {
            return Err(err(
                s,
                "expected a current point (D02 or a previous operation) before D01, found none"
                    .into(),
            ));
        };
        // The path of the segment, excluding its start point.
        let path: Vec<[f64; 2]> = match mode {
            Interp::Linear => vec![to],
            Interp::Clockwise | Interp::CounterClockwise => {
                arc_path(s, p, to, i, j, mode, self.multi)?
            }
        };
        grow(&mut self.img.path_bbox, p);
        for &q in &path {
            grow(&mut self.img.path_bbox, q);
        }
        if self.region.is_some() {
            if self.contour.is_empty() {
                self.contour.push(p);
            }
            self.contour.extend(path);
        } else {
            let Some(code) = self.current else {
                return Err(err(
                    s,
                    "expected an aperture selected (Dnn) before a draw (D01), found none".into(),
                ));
            };
            let ap = &self.apertures[&code];
            let mut prev = p;
            match ap {
                ApertureShape::Circle { d_m, .. } => {
                    let r = 0.5 * d_m * self.xf.scale;
                    if r > 0.0 {
                        if path.is_empty() {
                            push(&mut self.img, self.dark, vec![disc(p, r)]);
                        }
                        for &q in &path {
                            push(&mut self.img, self.dark, vec![capsule(prev, q, r)]);
                            prev = q;
                        }
                    }
                }
                ApertureShape::Rect { .. } if mode == Interp::Linear => {
                    let c = &aperture_contours(ap, &self.xf)[0];
                    let pts = c
                        .iter()
                        .flat_map(|v| [[v[0] + p[0], v[1] + p[1]], [v[0] + to[0], v[1] + to[1]]])
                        .collect();
                    push(&mut self.img, self.dark, vec![convex_hull(pts)]);
                }
                _ => {
                    return Err(err(
                        s,
                        format!("expected a circular aperture for a draw (a rectangle for straight draws only), found D{code} = {ap:?}"),
                    ))
                }
            }
        }
        self.pt = Some(to);
        Ok(())
    }
}

/// The path of a circular arc from `p` to `to` (excluding `p`) with centre offsets `i`,
/// `j`: signed (G75, `multi`), or unsigned with the centre giving an arc of at most 90°
/// (G74).
fn arc_path(
    s: &Stmt,
    p: [f64; 2],
    to: [f64; 2],
    i: Option<f64>,
    j: Option<f64>,
    mode: Interp,
    multi: bool,
) -> Result<Vec<[f64; 2]>, GerberError> {
    let cw = mode == Interp::Clockwise;
    let (ii, jj) = (i.unwrap_or(0.0), j.unwrap_or(0.0));
    let centre = if multi {
        [p[0] + ii, p[1] + jj]
    } else {
        // G74: I, J unsigned; the centre is the one giving an
        // arc of at most 90° in the given direction.
        let mut best: Option<([f64; 2], f64)> = None;
        for (sx, sy) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
            let c = [p[0] + sx * ii.abs(), p[1] + sy * jj.abs()];
            let a0 = (p[1] - c[1]).atan2(p[0] - c[0]);
            let a1 = (to[1] - c[1]).atan2(to[0] - c[0]);
            let sw = (if cw { a0 - a1 } else { a1 - a0 }).rem_euclid(2.0 * std::f64::consts::PI);
            let dr = ((p[0] - c[0]).hypot(p[1] - c[1]) - (to[0] - c[0]).hypot(to[1] - c[1])).abs();
            if sw <= std::f64::consts::FRAC_PI_2 + 1e-9 && best.is_none_or(|b| dr < b.1) {
                best = Some((c, dr));
            }
        }
        match best {
            Some((c, _)) => c,
            None => {
                return Err(err(
                    s,
                    "expected a single-quadrant (G74) arc of at most 90°, found none matching I, J"
                        .into(),
                ))
            }
        }
    };
    let r0 = (p[0] - centre[0]).hypot(p[1] - centre[1]);
    let r1 = (to[0] - centre[0]).hypot(to[1] - centre[1]);
    if (r0 - r1).abs() > 5e-6 + 1e-3 * r0.max(r1) {
        return Err(err(
            s,
            format!(
                "expected the arc's start and end at the same distance from its centre, found {:.6} mm and {:.6} mm",
                r0 * 1e3,
                r1 * 1e3
            ),
        ));
    }
    Ok(if !multi && (p[0] - to[0]).hypot(p[1] - to[1]) <= 1e-12 {
        Vec::new()
    } else {
        arc_points(p, to, centre, cw)
    })
}

/// Sorted disjoint intervals.
type Intervals = Vec<(f64, f64)>;

fn union(a: &Intervals, b: &Intervals) -> Intervals {
    let mut all: Vec<(f64, f64)> = a.iter().chain(b.iter()).copied().collect();
    all.sort_by(|p, q| p.0.total_cmp(&q.0));
    let mut out: Intervals = Vec::with_capacity(all.len());
    for (l, r) in all {
        match out.last_mut() {
            Some(last) if l <= last.1 => last.1 = last.1.max(r),
            _ => out.push((l, r)),
        }
    }
    out
}

fn subtract(a: &Intervals, b: &Intervals) -> Intervals {
    let mut out = Vec::with_capacity(a.len() + b.len());
    let mut k = 0;
    for &(l, r) in a {
        let mut lo = l;
        while k < b.len() && b[k].1 <= lo {
            k += 1;
        }
        let mut m = k;
        while m < b.len() && b[m].0 < r {
            if b[m].0 > lo {
                out.push((lo, b[m].0));
            }
            lo = lo.max(b[m].1);
            m += 1;
        }
        if lo < r {
            out.push((lo, r));
        }
    }
    out
}

/// The x-intervals of a feature on the horizontal line y: even–odd over its contours,
/// or, for a macro flash, its primitives combined in order.
fn feature_intervals(f: &Feature, y: f64, xs: &mut Vec<f64>) -> Intervals {
    if f.parts.is_empty() {
        return contour_intervals(&f.contours, y, xs);
    }
    let mut acc: Intervals = Vec::new();
    let mut k = 0;
    for &(n, on) in &f.parts {
        let iv = contour_intervals(&f.contours[k..k + n], y, xs);
        k += n;
        if iv.is_empty() {
            continue;
        }
        acc = if on {
            union(&acc, &iv)
        } else {
            subtract(&acc, &iv)
        };
    }
    acc
}

/// The x-intervals of `contours` on the horizontal line y, even–odd.
fn contour_intervals(contours: &[Vec<[f64; 2]>], y: f64, xs: &mut Vec<f64>) -> Intervals {
    xs.clear();
    for c in contours {
        let n = c.len();
        for k in 0..n {
            let (a, b) = (c[k], c[(k + 1) % n]);
            if (a[1] <= y) != (b[1] <= y) {
                xs.push(a[0] + (y - a[1]) * (b[0] - a[0]) / (b[1] - a[1]));
            }
        }
    }
    xs.sort_by(|p, q| p.total_cmp(q));
    xs.chunks_exact(2)
        .filter(|p| p[1] > p[0])
        .map(|p| (p[0], p[1]))
        .collect()
}

/// Coverage fraction of each cell of the `nx × ny` grid over `extent` (rows from the
/// lowest, `values[j * nx + i]`), exact along x, midpoint rule in y over [`SUB_ROWS`]
/// sub-rows per cell cut further at every horizontal edge (exact for axis-aligned shapes).
pub fn rasterize(img: &Image, extent: &Rect, nx: usize, ny: usize) -> Grid {
    let dx = (extent.x1 - extent.x0) / nx as f64;
    let dy = (extent.y1 - extent.y0) / ny as f64;
    // Features touching each row of cells, in drawing order.
    let mut rows: Vec<Vec<u32>> = vec![Vec::new(); ny];
    for (k, f) in img.features.iter().enumerate() {
        let b = &f.bbox;
        if b.x1 < extent.x0 || b.x0 > extent.x1 || b.y1 < extent.y0 || b.y0 > extent.y1 {
            continue;
        }
        let j0 = (((b.y0 - extent.y0) / dy).floor().max(0.0) as usize).min(ny - 1);
        let j1 = (((b.y1 - extent.y0) / dy).floor().max(0.0) as usize).min(ny - 1);
        for r in &mut rows[j0..=j1] {
            r.push(k as u32);
        }
    }
    let mut values = vec![0.0; nx * ny];
    let mut xs = Vec::new();
    let mut cuts: Vec<f64> = Vec::new();
    for (j, feats) in rows.iter().enumerate() {
        // Slabs: the SUB_ROWS equal sub-rows, further cut at every horizontal edge inside
        // the row, so that a horizontal edge never falls inside a slab (the midpoint rule
        // is then exact on every slab between vertices of sloped edges).
        let (ya, yb) = (extent.y0 + j as f64 * dy, extent.y0 + (j + 1) as f64 * dy);
        cuts.clear();
        cuts.extend((0..=SUB_ROWS).map(|s| ya + s as f64 * dy / SUB_ROWS as f64));
        for &k in feats {
            for c in &img.features[k as usize].contours {
                for (q, p) in c.iter().zip(c.iter().cycle().skip(1)) {
                    if q[1] == p[1] && q[1] > ya && q[1] < yb {
                        cuts.push(q[1]);
                    }
                }
            }
        }
        cuts.sort_by(|a, b| a.total_cmp(b));
        cuts.dedup();
        for slab in cuts.windows(2) {
            let h = slab[1] - slab[0];
            if h <= 0.0 {
                continue;
            }
            let y = 0.5 * (slab[0] + slab[1]);
            let w = h / (dy * dx);
            let mut set: Intervals = Vec::new();
            for &k in feats {
                let f = &img.features[k as usize];
                if y < f.bbox.y0 || y > f.bbox.y1 {
                    continue;
                }
                let iv = feature_intervals(f, y, &mut xs);
                if iv.is_empty() {
                    continue;
                }
                set = if f.dark {
                    union(&set, &iv)
                } else {
                    subtract(&set, &iv)
                };
            }
            for (l, r) in set {
                let (l, r) = (l.max(extent.x0), r.min(extent.x1));
                if r <= l {
                    continue;
                }
                let i0 = (((l - extent.x0) / dx).floor() as usize).min(nx - 1);
                let i1 = (((r - extent.x0) / dx).floor() as usize).min(nx - 1);
                for i in i0..=i1 {
                    let c0 = extent.x0 + i as f64 * dx;
                    let len = (r.min(c0 + dx) - l.max(c0)).max(0.0);
                    values[j * nx + i] += len * w;
                }
            }
        }
    }
    for v in &mut values {
        *v = v.clamp(0.0, 1.0);
    }
    Grid { nx, ny, values }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn st(cmd: Cmd) -> Stmt {
        Stmt {
            pos: SrcPos {
                line: 1,
                command: "test".into(),
            },
            cmd,
        }
    }
    fn op(d: u8, x: f64, y: f64) -> Cmd {
        Cmd::Op {
            d,
            x: Some(x),
            y: Some(y),
            i: None,
            j: None,
        }
    }
    fn total(img: &Image, e: &Rect, n: usize) -> f64 {
        let g = rasterize(img, e, n, n);
        let cell = (e.x1 - e.x0) * (e.y1 - e.y0) / (n * n) as f64;
        g.values.iter().sum::<f64>() * cell
    }
    const E: Rect = Rect {
        x0: -2e-3,
        y0: -2e-3,
        x1: 6e-3,
        y1: 6e-3,
    };

    #[test]
    fn circle_flash_area_is_pi_r_squared() {
        let r = 0.7e-3;
        let img = render(&[
            st(Cmd::ApertureDef {
                code: 10,
                shape: ApertureShape::Circle {
                    d_m: 2.0 * r,
                    hole_m: Some(0.4e-3),
                },
            }),
            st(Cmd::Select(10)),
            st(op(3, 1e-3, 1.3e-3)),
        ])
        .unwrap();
        let exact = std::f64::consts::PI * (r * r - 0.2e-3 * 0.2e-3);
        let got = total(&img, &E, 80);
        assert!((got / exact - 1.0).abs() < 2e-4, "{got:e} vs {exact:e}");
    }

    #[test]
    fn stroked_segment_is_rectangle_plus_two_half_discs() {
        let (r, p, q) = (0.25e-3, [0.1e-3, 0.3e-3], [4.2e-3, 2.9e-3]);
        let img = render(&[
            st(Cmd::ApertureDef {
                code: 11,
                shape: ApertureShape::Circle {
                    d_m: 2.0 * r,
                    hole_m: None,
                },
            }),
            st(Cmd::Select(11)),
            st(Cmd::Interp(Interp::Linear)),
            st(op(2, p[0], p[1])),
            st(op(1, q[0], q[1])),
        ])
        .unwrap();
        let len = (q[0] - p[0]).hypot(q[1] - p[1]);
        let exact = 2.0 * r * len + std::f64::consts::PI * r * r;
        let got = total(&img, &E, 80);
        assert!((got / exact - 1.0).abs() < 2e-4, "{got:e} vs {exact:e}");
        assert_eq!(
            img.path_bbox,
            Some(Rect {
                x0: p[0],
                y0: p[1],
                x1: q[0],
                y1: q[1]
            })
        );
    }

    #[test]
    fn clear_hole_in_dark_region_and_arc_region() {
        // A 4 × 3 mm dark region, a clear 1 mm disc flashed inside, then a dark region
        // bounded by a half circle of radius 1 mm (G03 arc) over the hole's lower half.
        let mut s = vec![
            st(Cmd::ApertureDef {
                code: 10,
                shape: ApertureShape::Circle {
                    d_m: 1e-3,
                    hole_m: None,
                },
            }),
            st(Cmd::Interp(Interp::Linear)),
            st(Cmd::Region(true)),
            st(op(2, 0.0, 0.0)),
            st(op(1, 4e-3, 0.0)),
            st(op(1, 4e-3, 3e-3)),
            st(op(1, 0.0, 3e-3)),
            st(op(1, 0.0, 0.0)),
            st(Cmd::Region(false)),
            st(Cmd::Polarity { dark: false }),
            st(Cmd::Select(10)),
            st(op(3, 2e-3, 1.5e-3)),
        ];
        let img = render(&s).unwrap();
        let pi = std::f64::consts::PI;
        let exact = 12e-6 - pi * 0.25e-6;
        let got = total(&img, &E, 64);
        assert!((got / exact - 1.0).abs() < 2e-4, "{got:e} vs {exact:e}");
        // Then a dark half disc of radius 1 mm: G03 from (0, 5) mm about (1, 5) mm to
        // (2, 5) mm passes through (1, 4) mm, closed by a straight edge.
        s.extend([
            st(Cmd::Polarity { dark: true }),
            st(Cmd::Region(true)),
            st(op(2, 0.0, 5e-3)),
            st(Cmd::Interp(Interp::CounterClockwise)),
            st(Cmd::Op {
                d: 1,
                x: Some(2e-3),
                y: Some(5e-3),
                i: Some(1e-3),
                j: Some(0.0),
            }),
            st(Cmd::Interp(Interp::Linear)),
            st(op(1, 0.0, 5e-3)),
            st(Cmd::Region(false)),
        ]);
        let img = render(&s).unwrap();
        let got2 = total(&img, &E, 64);
        let half = 0.5 * pi * 1e-6;
        assert!(
            ((got2 - got) / half - 1.0).abs() < 5e-4,
            "{:e} vs {half:e}",
            got2 - got
        );
    }

    #[test]
    fn step_and_repeat_copies_and_errors_name_the_statement() {
        let s = [
            st(Cmd::ApertureDef {
                code: 12,
                shape: ApertureShape::Rect {
                    w_m: 0.5e-3,
                    h_m: 0.25e-3,
                    hole_m: None,
                },
            }),
            st(Cmd::StepRepeat {
                nx: 3,
                ny: 2,
                dx_m: 1e-3,
                dy_m: 1e-3,
            }),
            st(Cmd::Select(12)),
            st(op(3, 0.0, 0.0)),
            st(Cmd::StepRepeatEnd),
        ];
        let img = render(&s).unwrap();
        assert_eq!(img.features.len(), 6);
        let got = total(&img, &E, 64);
        assert!((got / (6.0 * 0.125e-6) - 1.0).abs() < 1e-9, "{got:e}");
        let bad = [Stmt {
            pos: SrcPos {
                line: 7,
                command: "D11".into(),
            },
            cmd: Cmd::Select(11),
        }];
        let e = render(&bad).unwrap_err().to_string();
        assert!(
            e.contains("line 7") && e.contains("D11") && e.contains("undefined"),
            "{e}"
        );
    }

    /// Area of a primitive's contours (even–odd, from the shoelace of each contour; the
    /// primitives' contours do not overlap).
    fn prim_area(p: &MacroPrimitive) -> f64 {
        p.contours
            .iter()
            .map(|c| {
                let n = c.len();
                0.5 * (0..n)
                    .map(|k| c[k][0] * c[(k + 1) % n][1] - c[(k + 1) % n][0] * c[k][1])
                    .sum::<f64>()
            })
            .map(f64::abs)
            .sum()
    }

    /// Every macro primitive against its closed-form area (mm units, so m² × 1e6), and
    /// rotation about the macro origin (not the primitive's centre).
    #[test]
    fn macro_primitives_have_their_closed_form_areas_and_rotate_about_the_origin() {
        let pi = std::f64::consts::PI;
        let a = |code: u32, p: &[f64]| {
            prim_area(&macro_primitive(code, p, 1e-3).unwrap().unwrap()) * 1e6
        };
        let close = |got: f64, want: f64| {
            assert!((got / want - 1.0).abs() < 1e-6, "{got} vs {want}");
        };
        close(a(1, &[1.0, 1.5, 3.0, 4.0]), pi * 0.75 * 0.75);
        close(a(20, &[1.0, 0.3, 0.0, 0.0, 3.0, 4.0, 17.0]), 0.3 * 5.0);
        close(a(21, &[1.0, 2.0, 0.5, 1.0, 1.0, 30.0]), 1.0);
        close(
            a(4, &[1.0, 3.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.0, 0.0, 0.0, 45.0]),
            1.0,
        );
        let r: f64 = 0.8;
        close(
            a(5, &[1.0, 6.0, 1.0, 1.0, 2.0 * r, 10.0]),
            3.0 * r * r * (pi / 3.0).sin(),
        );
        // Thermal: the annulus minus the cross of gap width 0.3 (four rectangles of
        // 0.15 × the ring, less the overlap square counted in none since ri > g).
        let (ro, ri, g) = (1.0f64, 0.6f64, 0.15f64);
        let strip = |r: f64| 2.0 * (g * (r * r - g * g).sqrt() + r * r * (g / r).asin());
        let cross_in_ring = 2.0 * (strip(ro) - strip(ri)) - 0.0;
        // Two strips through the centre overlap in the central square |x|, |y| ≤ g,
        // which lies inside the inner disc (g√2 < ri), so it adds nothing to the ring.
        // Its arcs are chords of sagitta ≤ FLATTEN_TOL_M (not area-corrected like
        // `disc`): ~1e-4 of the area at these sizes, well below the 1 % coverage bound.
        let th = a(7, &[0.0, 0.0, 2.0 * ro, 2.0 * ri, 2.0 * g, 0.0]);
        let want = pi * (ro * ro - ri * ri) - cross_in_ring;
        assert!(th <= want && th / want > 1.0 - 3e-4, "{th} vs {want}");
        // Rotation about the origin: a circle at (2, 0) mm rotated 90° sits at (0, 2).
        let p = macro_primitive(1, &[1.0, 0.5, 2.0, 0.0, 90.0], 1e-3)
            .unwrap()
            .unwrap();
        let n = p.contours[0].len() as f64;
        let (cx, cy) = p.contours[0]
            .iter()
            .fold((0.0, 0.0), |s, v| (s.0 + v[0] / n, s.1 + v[1] / n));
        assert!(
            cx.abs() < 1e-12 && (cy - 2e-3).abs() < 1e-12,
            "({cx}, {cy})"
        );
        // Exposure off, comments.
        assert!(
            !macro_primitive(1, &[0.0, 1.0, 0.0, 0.0], 1e-3)
                .unwrap()
                .unwrap()
                .exposure
        );
        assert!(macro_primitive(0, &[], 1e-3).unwrap().is_none());
    }
}
