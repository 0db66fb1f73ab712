//! The board's geometry as a gmsh script (OpenCASCADE kernel): the outline with its holes
//! cut out, fragmented by every line the truth's materials change along (copper regions and
//! cut-outs, the clamped annuli of the joints, an underfill disc), so that the mesh conforms
//! to each of them and every element lies wholly inside one material region.
//!
//! Lengths in the script are millimetres (the unit system of the solver deck). The mesh is
//! all 8-node quadrilaterals: Frontal-Delaunay triangles recombined, then every element split
//! into quads (`Mesh.SubdivisionAlgorithm = 1`), which halves the element size, so the
//! characteristic length asked for is twice the wanted element size.

use std::fmt::Write;

use crate::fem::Board;

/// A disc the mesh must conform to (centre and radius in metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Disc {
    pub x_m: f64,
    pub y_m: f64,
    pub r_m: f64,
}

/// The gmsh script for `board` with element size `element_size_m`, conforming to the copper
/// regions and cut-outs and to `discs` (clamped patches, underfill).
pub fn geo_script(board: &Board, element_size_m: f64, discs: &[Disc]) -> String {
    let mm = |v: f64| 1e3 * v;
    let mut s = String::new();
    let _ = writeln!(s, "SetFactory(\"OpenCASCADE\");");
    let _ = writeln!(s, "Geometry.Tolerance = 1e-7;");
    let _ = writeln!(
        s,
        "Rectangle(1) = {{0, 0, 0, {}, {}}};",
        mm(board.length_x_m),
        mm(board.width_y_m)
    );
    let mut next_surface = 2usize;
    let mut hole_ids = Vec::new();
    for h in &board.holes {
        let _ = writeln!(
            s,
            "Disk({next_surface}) = {{{}, {}, 0, {}}};",
            mm(h.x_m),
            mm(h.y_m),
            mm(0.5 * h.diameter_m)
        );
        hole_ids.push(next_surface);
        next_surface += 1;
    }
    if hole_ids.is_empty() {
        let _ = writeln!(s, "b() = {{1}};");
    } else {
        let _ = writeln!(
            s,
            "b() = BooleanDifference{{ Surface{{1}}; Delete; }}{{ Surface{{{}}}; Delete; }};",
            join(&hole_ids)
        );
    }
    // Tool surfaces, each clipped to the board (the clipped pieces of a tool that crosses a
    // hole or the edge never become elements of their own).
    let mut tools: Vec<String> = Vec::new();
    let mut next_point = 1000usize;
    let mut next_curve = 1000usize;
    let mut add_tool = |s: &mut String, def: String, id: usize| {
        s.push_str(&def);
        let _ = writeln!(
            s,
            "t{id}() = BooleanIntersection{{ Surface{{{id}}}; Delete; }}{{ Surface{{b()}}; }};"
        );
        tools.push(format!("t{id}()"));
    };
    for layer in &board.copper {
        for region in layer.coverage.iter().chain(&layer.cutouts) {
            let outline = region.outline();
            let id = next_surface;
            next_surface += 1;
            let mut def = String::new();
            let first_point = next_point;
            for v in &outline {
                let _ = writeln!(
                    def,
                    "Point({next_point}) = {{{}, {}, 0}};",
                    mm(v[0]),
                    mm(v[1])
                );
                next_point += 1;
            }
            let first_curve = next_curve;
            for k in 0..outline.len() {
                let a = first_point + k;
                let b = first_point + (k + 1) % outline.len();
                let _ = writeln!(def, "Line({next_curve}) = {{{a}, {b}}};");
                next_curve += 1;
            }
            let curves: Vec<usize> = (first_curve..next_curve).collect();
            let _ = writeln!(def, "Curve Loop({id}) = {{{}}};", join(&curves));
            let _ = writeln!(def, "Plane Surface({id}) = {{{id}}};");
            add_tool(&mut s, def, id);
        }
    }
    for d in discs {
        let id = next_surface;
        next_surface += 1;
        let def = format!(
            "Disk({id}) = {{{}, {}, 0, {}}};\n",
            mm(d.x_m),
            mm(d.y_m),
            mm(d.r_m)
        );
        add_tool(&mut s, def, id);
    }
    if !tools.is_empty() {
        let _ = writeln!(
            s,
            "BooleanFragments{{ Surface{{b()}}; Delete; }}{{ Surface{{{}}}; Delete; }}",
            tools.join(", ")
        );
    }
    let _ = writeln!(
        s,
        "Mesh.CharacteristicLengthMax = {};",
        mm(2.0 * element_size_m)
    );
    // Frontal-Delaunay (6): the quad-oriented variant (8) crashes gmsh 4.8 on these fragments.
    let _ = writeln!(s, "Mesh.Algorithm = 6;");
    let _ = writeln!(s, "Mesh.RecombineAll = 1;");
    let _ = writeln!(s, "Mesh.SubdivisionAlgorithm = 1;");
    let _ = writeln!(s, "Mesh.ElementOrder = 2;");
    let _ = writeln!(s, "Mesh.SecondOrderIncomplete = 1;");
    let _ = writeln!(s, "Mesh.Optimize = 1;");
    s
}

fn join(ids: &[usize]) -> String {
    ids.iter()
        .map(|i| i.to_string())
        .collect::<Vec<_>>()
        .join(", ")
}
