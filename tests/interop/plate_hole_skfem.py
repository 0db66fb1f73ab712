"""Independent reference for the plate-with-a-hole verification test (src/fem/tests):
free vibration of a completely free square Kirchhoff plate with a central circular
hole, by scikit-fem with the C1-conforming quintic Argyris triangle on a `triangle`
(Shewchuk) mesh whose hole is a 256-gon.

Usage: plate_hole_skfem.py HOLE_DIAMETER_OVER_SIDE NU N_MODES
Prints JSON: {"lambda": [...], "lambda_coarse": [...], "n_dof": ...}, the frequency
parameters λ = ω a² √(ρh/D) of the first N_MODES elastic modes on a fine and a
coarser mesh (their difference bounds the discretisation error of the fine one).
"""

import json
import sys

import numpy as np
import scipy.sparse.linalg as spla
import triangle
from skfem import Basis, BilinearForm, ElementTriArgyris, MeshTri, asm
from skfem.helpers import dd, ddot, eye, trace


def solve(d_over_a, nu, n_modes, max_area, n_seg=256):
    a = 1.0
    r = 0.5 * d_over_a * a
    sq = [[0, 0], [a, 0], [a, a], [0, a]]
    th = 2 * np.pi * np.arange(n_seg) / n_seg
    circ = np.c_[0.5 + r * np.cos(th), 0.5 + r * np.sin(th)]
    verts = np.vstack([sq, circ])
    segs = [[i, (i + 1) % 4] for i in range(4)]
    segs += [[4 + i, 4 + (i + 1) % n_seg] for i in range(n_seg)]
    tri = triangle.triangulate(
        {"vertices": verts, "segments": np.array(segs), "holes": [[0.5, 0.5]]},
        f"pq30a{max_area}",
    )
    mesh = MeshTri(tri["vertices"].T, tri["triangles"].T)
    basis = Basis(mesh, ElementTriArgyris(), intorder=10)

    # Plate with D = 1 (E h³ / 12 (1 − ν²) = 1) and ρh = 1.
    @BilinearForm
    def stiff(u, v, w):
        def c(t):
            # D [(1 − ν) κ:κ + ν tr²κ] with D = 1.
            return (1 - nu) * t + nu * eye(trace(t), 2)

        return ddot(c(dd(u)), dd(v))

    @BilinearForm
    def mass(u, v, w):
        return u * v

    k = asm(stiff, basis)
    m = asm(mass, basis)
    n_rigid = 3
    vals = spla.eigsh(
        k, k=n_modes + n_rigid, M=m, sigma=-1.0, which="LM", return_eigenvectors=False
    )
    vals = np.sort(vals)[n_rigid:]
    return np.sqrt(vals) * a * a, k.shape[0]


def main():
    d_over_a, nu, n_modes = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
    coarse, _ = solve(d_over_a, nu, n_modes, 8e-3)
    fine, n_dof = solve(d_over_a, nu, n_modes, 2e-3)
    print(
        json.dumps(
            {"lambda": fine.tolist(), "lambda_coarse": coarse.tolist(), "n_dof": n_dof}
        )
    )


if __name__ == "__main__":
    main()
