#!/usr/bin/env python3
"""Write reference UFF files with the third-party package pyuff, plus a JSON of the exact values
handed to pyuff, for hbmu's UFF reader tests.

Usage: pyuff_write_fixtures.py OUTDIR

Writes OUTDIR/<name>.uff for each case and OUTDIR/expected.json:
  {"files": {"<name>.uff": {"rel_tol": t, "datasets": [ {...}, ... ]}}}
with one entry per dataset in file order. rel_tol is the relative precision of the printed
fields (12 significant digits for double precision 58 records, 6 for single precision and for
dataset 15, 17 for 2411/164).

pyuff (2.5) refuses to write function type 5 (transmissibility): that case is written as type 4
and the function-type field (record 6, columns 1-5) is then patched to 5 in the bytes.
"""
import json
import os
import sys

import numpy as np
import pyuff

rng = np.random.default_rng(20240607)


def values(n):
    """Magnitudes over many decades, both signs, with exact zeros."""
    v = rng.standard_normal(n) * 10.0 ** rng.uniform(-9, 4, n)
    v[::17] = 0.0
    return v


def f58(func_type, data, x, even, rsp_node, ref_node, binary=0, ord_data_type=None):
    d = pyuff.prepare_58(
        binary=binary,
        id1="hbmu pyuff fixture",
        id2="PCB-03 free",
        id3="07-Jun-24 12:00:00",
        id4="id line 4",
        id5="id line 5",
        func_type=func_type,
        ver_num=0,
        load_case_id=0,
        rsp_ent_name="BOARD",
        rsp_node=rsp_node,
        rsp_dir=3,
        ref_ent_name="HAMMER",
        ref_node=ref_node,
        ref_dir=3,
        ord_data_type=ord_data_type,
        num_pts=len(data),
        abscissa_spacing=1 if even else 0,
        abscissa_min=x[0],
        abscissa_inc=x[1] - x[0],
        z_axis_value=0.0,
        abscissa_spec_data_type=18,
        abscissa_len_unit_exp=0,
        abscissa_force_unit_exp=0,
        abscissa_temp_unit_exp=0,
        abscissa_axis_units_lab="Hz",
        ordinate_spec_data_type=11,
        ordinate_len_unit_exp=1,
        ordinate_force_unit_exp=-1,
        ordinate_temp_unit_exp=0,
        ordinate_axis_units_lab="m/s/N",
        orddenom_spec_data_type=13,
        orddenom_len_unit_exp=0,
        orddenom_force_unit_exp=1,
        orddenom_temp_unit_exp=0,
        orddenom_axis_units_lab="N",
        z_axis_spec_data_type=0,
        z_axis_len_unit_exp=0,
        z_axis_force_unit_exp=0,
        z_axis_temp_unit_exp=0,
        z_axis_axis_units_lab="NONE",
        data=data,
        x=x,
    )
    return d


def expect58(d, func_type, ord_data_type, even):
    data = np.asarray(d["data"])
    e = {
        "type": 58,
        "func_type": func_type,
        "ord_data_type": ord_data_type,
        "even": even,
        "num_pts": int(len(data)),
        "rsp_node": int(d["rsp_node"]),
        "rsp_dir": int(d["rsp_dir"]),
        "ref_node": int(d["ref_node"]),
        "ref_dir": int(d["ref_dir"]),
        "rsp_ent_name": d["rsp_ent_name"],
        "ref_ent_name": d["ref_ent_name"],
        "id1": d["id1"],
        "abscissa_units": d["abscissa_axis_units_lab"],
        "ordinate_units": d["ordinate_axis_units_lab"],
        "ordinate_len_exp": d["ordinate_len_unit_exp"],
        "ordinate_force_exp": d["ordinate_force_unit_exp"],
        "x": [float(v) for v in d["x"]],
    }
    if np.iscomplexobj(data):
        e["re"] = [float(v) for v in data.real]
        e["im"] = [float(v) for v in data.imag]
    else:
        e["re"] = [float(v) for v in data]
    return e


def nodes(n):
    ids = np.arange(1, n + 1) * 7
    x = rng.uniform(0, 80, n)
    y = rng.uniform(0, 50, n)
    z = rng.uniform(-1, 1, n) * 1e-3
    return ids, x, y, z


def main():
    out = sys.argv[1]
    os.makedirs(out, exist_ok=True)
    files = {}

    # 1. A campaign-like file: 164 (mm), 2411, FRFs (complex double), coherence (real double).
    name = "campaign_like.uff"
    path = os.path.join(out, name)
    u = pyuff.UFF(path)
    exp = []
    d164 = pyuff.prepare_164(units_code=5, units_description="mm (milli newton)", temp_mode=2,
                             length=1000.0, force=1000.0, temp=1.0, temp_offset=273.15)
    exp.append({"type": 164, "units_code": 5, "description": "mm (milli newton)", "temp_mode": 2,
                "length": 1000.0, "force": 1000.0, "temp": 1.0, "temp_offset": 273.15})
    ids, x, y, z = nodes(9)
    d2411 = pyuff.prepare_2411(node_nums=ids, def_cs=np.zeros(9, int), disp_cs=np.zeros(9, int),
                               color=np.full(9, 11), x=x, y=y, z=z)
    exp.append({"type": 2411, "node_nums": [int(i) for i in ids], "color": [11] * 9,
                "x": list(map(float, x)), "y": list(map(float, y)), "z": list(map(float, z))})
    dsets = [d164, d2411]
    freq = np.arange(0, 2001) * 0.625 + 5.0
    for k in range(3):
        data = values(len(freq)) + 1j * values(len(freq))
        d = f58(4, data, freq, True, rsp_node=int(ids[k]), ref_node=int(ids[-1]))
        dsets.append(d)
        exp.append(expect58(d, 4, 6, True))
    coh = rng.uniform(0, 1, len(freq))
    d = f58(6, coh, freq, True, rsp_node=int(ids[0]), ref_node=int(ids[-1]))
    dsets.append(d)
    exp.append(expect58(d, 6, 4, True))
    u.write_sets(dsets, mode="overwrite")
    files[name] = {"rel_tol": 5e-12, "datasets": exp}

    # 2. Complex single precision (ASCII 6E13.5) and real single precision.
    name = "single.uff"
    path = os.path.join(out, name)
    u = pyuff.UFF(path)
    freq = np.arange(0, 37) * 2.5
    dc = f58(4, values(37) + 1j * values(37), freq, True, 3, 9, ord_data_type=5)
    dr = f58(6, rng.uniform(0, 1, 37), freq, True, 3, 9, ord_data_type=2)
    u.write_sets([dc, dr], mode="overwrite", force_double=False)
    files[name] = {"rel_tol": 5e-6, "datasets": [expect58(dc, 4, 5, True), expect58(dr, 6, 2, True)]}

    # 3. Uneven abscissa: real double (2(E13.5,E20.12)) and complex double (E13.5,2E20.12).
    name = "uneven.uff"
    path = os.path.join(out, name)
    u = pyuff.UFF(path)
    xu = np.cumsum(rng.uniform(0.5, 1.5, 23))
    dr = f58(6, rng.uniform(0, 1, 23), xu, False, 1, 2)
    dc = f58(4, values(23) + 1j * values(23), xu, False, 1, 2)
    u.write_sets([dr, dc], mode="overwrite")
    er, ec = expect58(dr, 6, 4, False), expect58(dc, 4, 6, False)
    files[name] = {"rel_tol": 5e-12, "x_rel_tol": 5e-6, "datasets": [er, ec]}

    # 4. Binary 58b, complex double (pyuff writes binary in double precision, native order).
    name = "binary.uff"
    path = os.path.join(out, name)
    u = pyuff.UFF(path)
    freq = np.arange(0, 101) * 1.25
    d1 = f58(4, values(101) + 1j * values(101), freq, True, 4, 9, binary=1)
    d2 = f58(6, rng.uniform(0, 1, 101), freq, True, 4, 9, binary=1)
    # pyuff 2.5 truncates the file when a binary set is written in "overwrite" mode (it reopens
    # the file with "wb" after the header), so binary sets are appended to a fresh file.
    if os.path.exists(path):
        os.remove(path)
    u.write_sets([d1, d2], mode="add")
    # Binary values are exact; 2.3e-16 allows the last-bit error of the reader's JSON parser.
    files[name] = {"rel_tol": 2.3e-16, "datasets": [expect58(d1, 4, 6, True), expect58(d2, 6, 4, True)]}

    # 5. Dataset 15 nodes and a transmissibility (type 5, patched; see module docstring).
    name = "ds15_transmissibility.uff"
    path = os.path.join(out, name)
    u = pyuff.UFF(path)
    ids, x, y, z = nodes(5)
    d15 = pyuff.prepare_15(node_nums=ids, def_cs=np.zeros(5, int), disp_cs=np.zeros(5, int),
                           color=np.zeros(5, int), x=x, y=y, z=z)
    freq = np.arange(0, 50) * 4.0 + 10.0
    dt = f58(4, values(50) + 1j * values(50), freq, True, int(ids[0]), int(ids[4]))
    u.write_sets([d15, dt], mode="overwrite")
    with open(path, "rb") as fh:
        raw = fh.read()
    lines = raw.split(b"\n")
    # Record 6 of the 58: the line after the 5 ID lines following the "    58" line.
    k58 = next(i for i, l in enumerate(lines) if l.startswith(b"    58"))
    rec6 = lines[k58 + 6]
    assert rec6[:5] == b"    4", rec6
    lines[k58 + 6] = b"    5" + rec6[5:]
    with open(path, "wb") as fh:
        fh.write(b"\n".join(lines))
    e15 = {"type": 15, "node_nums": [int(i) for i in ids], "color": [0] * 5,
           "x": list(map(float, x)), "y": list(map(float, y)), "z": list(map(float, z))}
    files[name] = {"rel_tol": 5e-12, "node_rel_tol": 5e-6,
                   "datasets": [e15, expect58(dt, 5, 6, True)]}

    # 6. A mode set as modal-analysis software hands it over: nodes, then one dataset 55 per
    #    mode: two normal modes (real shapes, X Y Z per node) and a complex mode.
    name = "modes.uff"
    path = os.path.join(out, name)
    u = pyuff.UFF(path)
    ids, x, y, z = nodes(6)
    d2411 = pyuff.prepare_2411(node_nums=ids, def_cs=np.zeros(6, int), disp_cs=np.zeros(6, int),
                               color=np.full(6, 11), x=x, y=y, z=z)
    exp = [{"type": 2411, "node_nums": [int(i) for i in ids], "color": [11] * 6,
            "x": list(map(float, x)), "y": list(map(float, y)), "z": list(map(float, z))}]
    dsets = [d2411]
    for mode_n, (freq_hz, zeta) in enumerate([(412.5, 0.011), (1033.75, 0.0085)], start=1):
        r = [values(6) for _ in range(3)]
        d = pyuff.prepare_55(model_type=1, id1="NONE", id2="NONE", id3="NONE", id4="NONE",
                             id5="NONE", analysis_type=2, data_ch=2, spec_data_type=8,
                             data_type=2, n_data_per_node=3, node_nums=ids, r1=r[0], r2=r[1],
                             r3=r[2], load_case=1, mode_n=mode_n, freq=freq_hz, modal_m=0.0,
                             modal_damp_vis=zeta, modal_damp_his=0.0)
        dsets.append(d)
        exp.append({"type": 55, "analysis_type": 2, "complex": False, "ndv": 3,
                    "mode_n": mode_n, "freq": freq_hz, "damp": zeta,
                    "node_nums": [int(i) for i in ids],
                    "re": [float(v) for k in range(6) for v in (r[0][k], r[1][k], r[2][k])]})
    sigma, wd = -25.0, 2 * np.pi * 1630.0
    c = [values(6) + 1j * values(6) for _ in range(3)]
    d = pyuff.prepare_55(model_type=1, id1="NONE", id2="NONE", id3="NONE", id4="NONE", id5="NONE",
                         analysis_type=3, data_ch=2, spec_data_type=8, data_type=5,
                         n_data_per_node=3, node_nums=ids, r1=c[0], r2=c[1], r3=c[2], load_case=1,
                         mode_n=3, eig=sigma + 1j * wd, modal_a=0j, modal_b=0j)
    dsets.append(d)
    wn = float(np.hypot(sigma, wd))
    exp.append({"type": 55, "analysis_type": 3, "complex": True, "ndv": 3, "mode_n": 3,
                "freq": wn / (2 * np.pi), "damp": -sigma / wn,
                "node_nums": [int(i) for i in ids],
                "re": [float(v.real) for k in range(6) for v in (c[0][k], c[1][k], c[2][k])],
                "im": [float(v.imag) for k in range(6) for v in (c[0][k], c[1][k], c[2][k])]})
    u.write_sets(dsets, mode="overwrite")
    files[name] = {"rel_tol": 5e-6, "datasets": exp}

    with open(os.path.join(out, "expected.json"), "w") as fh:
        json.dump({"files": files}, fh)


if __name__ == "__main__":
    main()
