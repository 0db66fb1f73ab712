#!/usr/bin/env python3
"""Write the small example campaign in data/example/campaign/ with the third-party `pyuff`.

This is the built-in campaign of the README's main job until the virtual lab writes richer
ones, and it doubles as an interop fixture: every UFF here is written by pyuff, not by hbmu.
Synthetic FRFs by modal superposition of plate-like shapes (not a physical board model):
3 boards, 2 free-free measurements each (mobility, hammer) and 1 bolted measurement
(transmissibility, base excitation), a 6 x 4 scan grid, 300 lines up to 3 kHz.

Usage: python3 data/example/make_example.py [OUTDIR]   (default: data/example/campaign)
Deterministic: fixed seed, fixed formats.
"""
import os
import sys

import numpy as np
import pyuff

OUT = sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "campaign")
rng = np.random.default_rng(20261122)

LX, LY = 80.0, 50.0  # mm (grid inset 9 mm: clear of the bolt holes at 5 mm)
NX, NY = 6, 4
xs = np.linspace(9.0, LX - 9.0, NX)
ys = np.linspace(9.0, LY - 9.0, NY)
grid = [(x, y) for y in ys for x in xs]
nodes = list(range(1, len(grid) + 1))
freq = np.arange(300) * 10.0  # 0 .. 2990 Hz

# (frequency Hz, damping ratio, shape function of (x, y) in mm)
def shapes(scale):
    return [
        (780.0 * scale, 0.010, lambda x, y: (x / LX - 0.5) * (y / LY - 0.5) * 4),  # torsion
        (955.0 * scale, 0.008, lambda x, y: np.cos(2 * np.pi * x / LX)),  # bending x
        (1870.0 * scale, 0.012, lambda x, y: np.cos(2 * np.pi * y / LY)),  # bending y
        (2560.0 * scale, 0.009, lambda x, y: np.cos(3 * np.pi * x / LX)),
    ]

def frf(modes, resp, ref, kind):
    w = 2 * np.pi * freq
    h = np.zeros_like(freq, dtype=complex)
    for fn, zeta, phi in modes:
        wn = 2 * np.pi * fn
        a = phi(*resp) * phi(*ref)
        h += a * 1j * w / (wn**2 - w**2 + 2j * zeta * wn * w) / 0.013  # mobility, 13 g
    if kind == 5:
        h = 1.0 + h * 0.5  # transmissibility-like: rigid 1 plus resonances
    noise = (rng.standard_normal(len(freq)) + 1j * rng.standard_normal(len(freq))) * 1e-4
    return h + noise

def write_measurement(path, board_scale, setup, with_units):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    if os.path.exists(path):
        os.remove(path)
    uf = pyuff.UFF(path)
    modes = shapes(board_scale)
    length_scale = 1.0
    if with_units:
        uf.write_sets(pyuff.prepare_164(units_code=1, units_description="SI", temp_mode=1,
                                        length=1.0, force=1.0, temp=1.0, temp_offset=273.15), "add")
        length_scale = 1e-3  # coordinates written in metres
    ref = (13.0, 7.0) if setup == "free" else (-30.0, 25.0)  # hammer point off every nodal line
    ref_node = 100
    all_nodes = nodes + [ref_node]
    pts = grid + [ref]
    uf.write_sets(pyuff.prepare_2411(node_nums=np.array(all_nodes), def_cs=np.zeros(len(all_nodes), dtype=int),
                                     disp_cs=np.zeros(len(all_nodes), dtype=int), color=np.full(len(all_nodes), 8, dtype=int),
                                     x=np.array([p[0] for p in pts]) * length_scale,
                                     y=np.array([p[1] for p in pts]) * length_scale,
                                     z=np.zeros(len(all_nodes))), "add")
    kind = 4 if setup == "free" else 5
    # pyuff (2.5) refuses to write function type 5 (transmissibility), which the contract
    # prescribes for bolted measurements: it is written as type 4 and record 6's first field
    # (I10, "function type") is patched below, exactly as a post-processing script would.
    for n, p in zip(nodes, grid):
        if setup == "bolted" and n == 7:
            continue  # the vibrometer marked this point invalid
        data = frf(modes, p, ref if setup == "free" else (LX / 2, LY / 2), kind)
        uf.write_sets(pyuff.prepare_58(
            binary=0, id1="hbmu example", id2=f"node {n}", id3="synthetic", id4="", id5="",
            func_type=4, ver_num=0, load_case_id=0, rsp_ent_name="PCB", rsp_node=n, rsp_dir=3,
            ref_ent_name="REF", ref_node=ref_node, ref_dir=3, ord_data_type=6, num_pts=len(freq),
            abscissa_spacing=1, abscissa_min=0.0, abscissa_inc=10.0, z_axis_value=0.0,
            abscissa_spec_data_type=18, abscissa_len_unit_exp=0, abscissa_force_unit_exp=0,
            abscissa_temp_unit_exp=0, abscissa_axis_units_lab="Hz",
            ordinate_spec_data_type=11 if kind == 4 else 0, ordinate_len_unit_exp=1 if kind == 4 else 0,
            ordinate_force_unit_exp=0, ordinate_temp_unit_exp=0,
            ordinate_axis_units_lab="m/s" if kind == 4 else "",
            orddenom_spec_data_type=13 if kind == 4 else 0, orddenom_len_unit_exp=0,
            orddenom_force_unit_exp=1 if kind == 4 else 0, orddenom_temp_unit_exp=0,
            orddenom_axis_units_lab="N" if kind == 4 else "",
            z_axis_spec_data_type=0, z_axis_len_unit_exp=0, z_axis_force_unit_exp=0,
            z_axis_temp_unit_exp=0, z_axis_axis_units_lab="",
            data=data, x=freq, spec_data_type=18, byte_ordering=1, fp_format=2,
            n_ascii_lines=11, n_bytes=0), "add")
        if setup == "free" and n <= 3:
            coh = np.clip(0.98 + 0.01 * rng.standard_normal(len(freq)), 0, 1)
            uf.write_sets(pyuff.prepare_58(
                binary=0, id1="hbmu example", id2=f"coherence node {n}", id3="", id4="", id5="",
                func_type=6, ver_num=0, load_case_id=0, rsp_ent_name="PCB", rsp_node=n, rsp_dir=3,
                ref_ent_name="REF", ref_node=ref_node, ref_dir=3, ord_data_type=4, num_pts=len(freq),
                abscissa_spacing=1, abscissa_min=0.0, abscissa_inc=10.0, z_axis_value=0.0,
                abscissa_spec_data_type=18, abscissa_len_unit_exp=0, abscissa_force_unit_exp=0,
                abscissa_temp_unit_exp=0, abscissa_axis_units_lab="Hz",
                ordinate_spec_data_type=0, ordinate_len_unit_exp=0, ordinate_force_unit_exp=0,
                ordinate_temp_unit_exp=0, ordinate_axis_units_lab="",
                orddenom_spec_data_type=0, orddenom_len_unit_exp=0, orddenom_force_unit_exp=0,
                orddenom_temp_unit_exp=0, orddenom_axis_units_lab="",
                z_axis_spec_data_type=0, z_axis_len_unit_exp=0, z_axis_force_unit_exp=0,
                z_axis_temp_unit_exp=0, z_axis_axis_units_lab="",
                data=coh, x=freq, spec_data_type=18, byte_ordering=1, fp_format=2,
                n_ascii_lines=11, n_bytes=0), "add")
    if kind == 5:
        with open(path) as f:
            lines = f.read().split("\n")
        for i in range(len(lines) - 7):
            if lines[i].strip() == "58" and lines[i + 6][:10].strip() == "4":
                lines[i + 6] = f"{5:10d}" + lines[i + 6][10:]
        with open(path, "w") as f:
            f.write("\n".join(lines))


rows = ["measurement_id,board_id,setup,file,bolt_set,torque_nm,temperature_c,date,operator,notes,rig"]
boards = {"PCB-01": 1.000, "PCB-02": 1.012, "PCB-03": 0.991}
k = 0
for b, s in boards.items():
    for rep in range(2):
        k += 1
        mid = f"M{k:03d}"
        write_measurement(os.path.join(OUT, "vibrometer", f"{mid}.uff"), s, "free", with_units=(k % 2 == 0))
        rows.append(f'{mid},{b},free,vibrometer/{mid}.uff,,,{21.0 + 0.3 * k:.1f},2026-11-0{rep + 1}T09:{10 + k:02d}:00,ana,"foam, soft",A')
    k += 1
    mid = f"M{k:03d}"
    write_measurement(os.path.join(OUT, "vibrometer", f"{mid}.uff"), s * 1.05, "bolted", with_units=False)
    rows.append(f'{mid},{b},bolted,vibrometer/{mid}.uff,BS-{k},0.5,22.0,2026-11-03,ben,"four bolts,\nhand tight",B')
with open(os.path.join(OUT, "campaign.csv"), "w", newline="") as f:
    f.write("\r\n".join(rows) + "\r\n")

os.makedirs(os.path.join(OUT, "scale"), exist_ok=True)
log = ["# Mettler Toledo XS205, MT-SICS SI command, readability 0.1 mg"]
t = 0
for b, s in boards.items():
    m = 13.0 * s
    log.append(f"2026-11-01T08:{t:02d}:00 {b} S D {m + 0.0312:10.4f} g"); t += 1
    log.append(f"2026-11-01T08:{t:02d}:00 {b} S I"); t += 1
    for _ in range(3):
        log.append(f"2026-11-01T08:{t:02d}:00 {b} S S {m + 0.00005 * rng.standard_normal():10.4f} g"); t += 1
log.append(f"2026-11-01T08:{t:02d}:00 PCB-03 S S {13.0 * 0.991 * 1000:10.1f} mg")
with open(os.path.join(OUT, "scale", "balance.log"), "w") as f:
    f.write("\n".join(log) + "\n")
print(f"example campaign written to {OUT}")
