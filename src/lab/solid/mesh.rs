//! The mid-plane mesh gmsh writes (8-node quadrilaterals), its extrusion into layers of
//! 20-node bricks, and the evaluation of a nodal field of the top face at arbitrary points.

use std::collections::BTreeMap;

/// A 2D mesh of 8-node serendipity quadrilaterals in millimetres, every element
/// counter-clockwise seen from +z (corners 0–3, then the mid-side nodes of the edges 0–1,
/// 1–2, 2–3, 3–0).
#[derive(Clone, Debug)]
pub struct Mesh2 {
    pub xy_mm: Vec<[f64; 2]>,
    pub quads: Vec<[usize; 8]>,
}

/// Parse gmsh's Abaqus-format output: the `*NODE` block and the 8-node quadrilateral
/// elements (`CPS8`); line elements are ignored, any other surface element is an error.
pub fn parse_gmsh_inp(text: &str) -> Result<Mesh2, String> {
    #[derive(PartialEq)]
    enum Block {
        None,
        Node,
        Quad,
        Skip,
    }
    let mut block = Block::None;
    let mut ids: BTreeMap<i64, usize> = BTreeMap::new();
    let mut xy = Vec::new();
    let mut raw_quads: Vec<(usize, [i64; 8])> = Vec::new();
    for (ln, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with("**") {
            continue;
        }
        if line.starts_with('*') {
            let up = line.to_ascii_uppercase();
            block = if up.starts_with("*NODE") {
                Block::Node
            } else if up.starts_with("*ELEMENT") {
                let ty = up
                    .split(',')
                    .find_map(|p| p.trim().strip_prefix("TYPE="))
                    .unwrap_or("")
                    .trim()
                    .to_string();
                match ty.as_str() {
                    "CPS8" | "S8" | "S8R" | "CPE8" => Block::Quad,
                    t if t.starts_with("T3D") || t.starts_with("B3") => Block::Skip,
                    other => {
                        return Err(format!(
                            "mesh line {}: expected only 8-node quadrilaterals, found element type {other}",
                            ln + 1
                        ))
                    }
                }
            } else {
                Block::Skip
            };
            continue;
        }
        let fields: Vec<&str> = line
            .split(',')
            .map(str::trim)
            .filter(|f| !f.is_empty())
            .collect();
        let bad = |what: &str| format!("mesh line {}: expected {what}, found `{line}`", ln + 1);
        match block {
            Block::Node => {
                if fields.len() < 3 {
                    return Err(bad("`id, x, y[, z]`"));
                }
                let id: i64 = fields[0].parse().map_err(|_| bad("a node id"))?;
                let x: f64 = fields[1].parse().map_err(|_| bad("x"))?;
                let y: f64 = fields[2].parse().map_err(|_| bad("y"))?;
                ids.insert(id, xy.len());
                xy.push([x, y]);
            }
            Block::Quad => {
                if fields.len() != 9 {
                    return Err(bad("an element id and 8 nodes"));
                }
                let mut n = [0i64; 8];
                for (k, f) in fields[1..].iter().enumerate() {
                    n[k] = f.parse().map_err(|_| bad("node ids"))?;
                }
                raw_quads.push((ln + 1, n));
            }
            Block::None | Block::Skip => {}
        }
    }
    let mut quads = Vec::with_capacity(raw_quads.len());
    for (ln, n) in raw_quads {
        let mut q = [0usize; 8];
        for k in 0..8 {
            q[k] = *ids
                .get(&n[k])
                .ok_or_else(|| format!("mesh line {ln}: node {} is not defined", n[k]))?;
        }
        quads.push(q);
    }
    if quads.is_empty() {
        return Err("mesh: expected 8-node quadrilaterals, found none".into());
    }
    let mut m = Mesh2 { xy_mm: xy, quads };
    m.orient();
    Ok(m)
}

impl Mesh2 {
    fn signed_area(&self, q: &[usize; 8]) -> f64 {
        (0..4)
            .map(|i| {
                let a = self.xy_mm[q[i]];
                let b = self.xy_mm[q[(i + 1) % 4]];
                a[0] * b[1] - b[0] * a[1]
            })
            .sum::<f64>()
            * 0.5
    }

    /// Make every element counter-clockwise (gmsh's surfaces come in either orientation).
    fn orient(&mut self) {
        for k in 0..self.quads.len() {
            if self.signed_area(&self.quads[k]) < 0.0 {
                let q = self.quads[k];
                self.quads[k] = [q[0], q[3], q[2], q[1], q[7], q[6], q[5], q[4]];
            }
        }
    }

    /// Centroid of element `e` (mean of its corners), mm.
    pub fn centroid(&self, e: usize) -> [f64; 2] {
        let q = &self.quads[e];
        let mut c = [0.0; 2];
        for &n in &q[..4] {
            c[0] += 0.25 * self.xy_mm[n][0];
            c[1] += 0.25 * self.xy_mm[n][1];
        }
        c
    }

    /// Area of element `e` (2×2 Gauss on the isoparametric map), mm².
    pub fn area(&self, e: usize) -> f64 {
        self.face_weights(e).iter().sum()
    }

    /// Row-sum-free lumping of the element's area to its nodes (HRZ: the diagonal of
    /// ∫ NᵢNⱼ dA scaled to the element's area), all positive, unlike the consistent
    /// nodal areas of the serendipity element (negative at the corners). Used to spread a
    /// contact stiffness or a mass over the nodes of a patch.
    pub fn face_weights(&self, e: usize) -> [f64; 8] {
        let g = [-(0.6f64).sqrt(), 0.0, (0.6f64).sqrt()];
        let w = [5.0 / 9.0, 8.0 / 9.0, 5.0 / 9.0];
        let q = &self.quads[e];
        let mut diag = [0.0; 8];
        let mut area = 0.0;
        for (i, &xi) in g.iter().enumerate() {
            for (j, &eta) in g.iter().enumerate() {
                let (n, dn) = shape(xi, eta);
                let mut jac = [[0.0; 2]; 2];
                for k in 0..8 {
                    let p = self.xy_mm[q[k]];
                    for d in 0..2 {
                        jac[0][d] += dn[k][0] * p[d];
                        jac[1][d] += dn[k][1] * p[d];
                    }
                }
                let det = jac[0][0] * jac[1][1] - jac[0][1] * jac[1][0];
                let wd = w[i] * w[j] * det;
                area += wd;
                for k in 0..8 {
                    diag[k] += wd * n[k] * n[k];
                }
            }
        }
        let s: f64 = diag.iter().sum();
        diag.map(|d| d * area / s)
    }

    /// Where `p` (mm) lies: the element and its local coordinates (ξ, η), or `None` when it
    /// is off the mesh (outside the board or in a hole).
    pub fn locate(&self, p: [f64; 2]) -> Option<(usize, [f64; 2])> {
        let tol = 1e-6;
        for (e, q) in self.quads.iter().enumerate() {
            let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
            for &n in q {
                for d in 0..2 {
                    lo[d] = lo[d].min(self.xy_mm[n][d]);
                    hi[d] = hi[d].max(self.xy_mm[n][d]);
                }
            }
            if p[0] < lo[0] - tol || p[0] > hi[0] + tol || p[1] < lo[1] - tol || p[1] > hi[1] + tol
            {
                continue;
            }
            // Newton on x(ξ, η) = p.
            let mut xi = [0.0f64; 2];
            let mut ok = false;
            for _ in 0..30 {
                let (n, dn) = shape(xi[0], xi[1]);
                let mut x = [0.0; 2];
                let mut jac = [[0.0; 2]; 2];
                for k in 0..8 {
                    let c = self.xy_mm[q[k]];
                    for d in 0..2 {
                        x[d] += n[k] * c[d];
                        jac[d][0] += dn[k][0] * c[d];
                        jac[d][1] += dn[k][1] * c[d];
                    }
                }
                let r = [p[0] - x[0], p[1] - x[1]];
                let det = jac[0][0] * jac[1][1] - jac[0][1] * jac[1][0];
                if det.abs() < 1e-300 {
                    break;
                }
                let dxi = [
                    (jac[1][1] * r[0] - jac[0][1] * r[1]) / det,
                    (-jac[1][0] * r[0] + jac[0][0] * r[1]) / det,
                ];
                xi[0] += dxi[0];
                xi[1] += dxi[1];
                if dxi[0].abs().max(dxi[1].abs()) < 1e-12 {
                    ok = true;
                    break;
                }
            }
            if ok && xi[0].abs() <= 1.0 + 1e-9 && xi[1].abs() <= 1.0 + 1e-9 {
                return Some((e, xi));
            }
        }
        None
    }

    /// Interpolate the nodal field `f` at local point `xi` of element `e`.
    pub fn interpolate(&self, f: &[f64], e: usize, xi: [f64; 2]) -> f64 {
        let (n, _) = shape(xi[0], xi[1]);
        self.quads[e].iter().zip(n).map(|(&k, nk)| nk * f[k]).sum()
    }
}

/// Shape functions of the 8-node serendipity quadrilateral and their (ξ, η) derivatives.
fn shape(xi: f64, eta: f64) -> ([f64; 8], [[f64; 2]; 8]) {
    const C: [[f64; 2]; 4] = [[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]];
    let mut n = [0.0; 8];
    let mut dn = [[0.0; 2]; 8];
    for k in 0..4 {
        let (a, b) = (C[k][0], C[k][1]);
        let (u, v) = (1.0 + a * xi, 1.0 + b * eta);
        n[k] = 0.25 * u * v * (a * xi + b * eta - 1.0);
        dn[k][0] = 0.25 * a * v * (2.0 * a * xi + b * eta);
        dn[k][1] = 0.25 * b * u * (a * xi + 2.0 * b * eta);
    }
    // Mid-side nodes 4 (η = −1), 5 (ξ = 1), 6 (η = 1), 7 (ξ = −1).
    n[4] = 0.5 * (1.0 - xi * xi) * (1.0 - eta);
    dn[4] = [-xi * (1.0 - eta), -0.5 * (1.0 - xi * xi)];
    n[5] = 0.5 * (1.0 + xi) * (1.0 - eta * eta);
    dn[5] = [0.5 * (1.0 - eta * eta), -(1.0 + xi) * eta];
    n[6] = 0.5 * (1.0 - xi * xi) * (1.0 + eta);
    dn[6] = [-xi * (1.0 + eta), 0.5 * (1.0 - xi * xi)];
    n[7] = 0.5 * (1.0 - xi) * (1.0 - eta * eta);
    dn[7] = [-0.5 * (1.0 - eta * eta), -(1.0 - xi) * eta];
    (n, dn)
}

/// One layer of the stack: its bottom and top height (mm) and, per 2D element, the material
/// class of its brick there (`None`: no brick, e.g. no copper over that element).
#[derive(Clone, Debug)]
pub struct Layer {
    pub z0_mm: f64,
    pub z1_mm: f64,
    pub class: Vec<Option<usize>>,
}

/// The extruded mesh: nodes with coordinates, 20-node bricks with their material class.
#[derive(Clone, Debug)]
pub struct Mesh3 {
    pub xyz_mm: Vec<[f64; 3]>,
    /// Per brick: its material class, its 2D element and its nodes in Abaqus C3D20 order.
    pub bricks: Vec<(usize, usize, [usize; 20])>,
    /// Per 2D node: the 3D node of the lowest and of the highest face above it.
    pub bottom: Vec<Option<usize>>,
    pub top: Vec<Option<usize>>,
}

/// Extrude `m` through `layers` (listed bottom to top, contiguous). A node exists only where
/// a brick uses it, so copper bricks sit only over the elements that carry copper.
pub fn extrude(m: &Mesh2, layers: &[Layer]) -> Mesh3 {
    let n2 = m.xy_mm.len();
    // Levels: 2 per layer (its mid-height and its top) above the first layer's bottom.
    let n_levels = 2 * layers.len() + 1;
    let z_of = |lev: usize| -> f64 {
        if lev == 0 {
            layers[0].z0_mm
        } else {
            let l = &layers[(lev - 1) / 2];
            if lev % 2 == 1 {
                0.5 * (l.z0_mm + l.z1_mm)
            } else {
                l.z1_mm
            }
        }
    };
    let mut id: Vec<Option<usize>> = vec![None; n_levels * n2];
    let mut xyz: Vec<[f64; 3]> = Vec::new();
    let mut node = |lev: usize, n: usize, xyz: &mut Vec<[f64; 3]>| -> usize {
        let slot = &mut id[lev * n2 + n];
        *slot.get_or_insert_with(|| {
            xyz.push([m.xy_mm[n][0], m.xy_mm[n][1], z_of(lev)]);
            xyz.len() - 1
        })
    };
    let mut bricks = Vec::new();
    let mut bottom = vec![None; n2];
    let mut top = vec![None; n2];
    for (li, layer) in layers.iter().enumerate() {
        let (lb, lm, lt) = (2 * li, 2 * li + 1, 2 * li + 2);
        for (e, q) in m.quads.iter().enumerate() {
            let Some(class) = layer.class[e] else {
                continue;
            };
            let mut b = [0usize; 20];
            for k in 0..4 {
                b[k] = node(lb, q[k], &mut xyz);
                b[4 + k] = node(lt, q[k], &mut xyz);
                b[8 + k] = node(lb, q[4 + k], &mut xyz);
                b[12 + k] = node(lt, q[4 + k], &mut xyz);
                b[16 + k] = node(lm, q[k], &mut xyz);
            }
            for k in 0..8 {
                let (nb, nt) = (
                    if k < 4 { b[k] } else { b[4 + k] },
                    if k < 4 { b[4 + k] } else { b[8 + k] },
                );
                let n = q[k];
                if bottom[n].is_none_or(|o: usize| xyz[nb][2] < xyz[o][2]) {
                    bottom[n] = Some(nb);
                }
                if top[n].is_none_or(|o: usize| xyz[nt][2] > xyz[o][2]) {
                    top[n] = Some(nt);
                }
            }
            bricks.push((class, e, b));
        }
    }
    Mesh3 {
        xyz_mm: xyz,
        bricks,
        bottom,
        top,
    }
}
