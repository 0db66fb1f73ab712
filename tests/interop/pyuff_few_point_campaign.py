#!/usr/bin/env python3
"""Few-point hammer campaigns as labs record them, written with the third-party pyuff, and the
check of what hbmu's ingest made of them (issue 53: accelerance and receptance, roving hammer).

Usage:
  pyuff_few_point_campaign.py write CAMPAIGN_DIR
  pyuff_few_point_campaign.py check CAMPAIGN_DIR INGEST_OUT_DIR
  pyuff_few_point_campaign.py check-modes EXTRACT_OUT_DIR

The truth is a closed-form two-mode mobility of a symmetric modal model,
  Y_jk(w) = sum_r i w phi_r(j) phi_r(k) / (w_r^2 - w^2 + 2 i zeta_r w_r w),
so that Y_jk = Y_kj (reciprocity). The campaign holds one board, three free-free measurements:
  M1  accelerometers at nodes 1, 2, 3, hammer at node 4, accelerance A = i w Y (m/s^2/N);
  M2  a roving hammer: the accelerometer fixed at node 1, the hammer at nodes 1..5, accelerance;
  M3  two points of receptance X = Y / (i w) (m/N) from a laser displacement sensor;
  M4  no FRF, only the two modes as a modal-analysis program exports them (dataset 55): the
      first a normal mode (analysis type 2, real shape), the second a complex one (type 3, its
      eigenvalue and a shape rotated by a complex factor), both as X, Y, Z translations.
`check` compares every response record of frf.parquet with the mobility Y at its (node,
reference) pair, and its `measured_as` with what was written; `check-modes` compares M4's
rows of extract's modes.parquet with the written modes (`source = uff55`). Each prints one
JSON line.
"""
import json
import os
import sys

import numpy as np
import pyuff

FREQ_HZ = np.arange(0.0, 2000.0, 2.5)
MODES = [(410.0, 0.012), (980.0, 0.009)]
NODES = {1: (5.0, 5.0), 2: (40.0, 25.0), 3: (75.0, 45.0), 4: (20.0, 40.0), 5: (60.0, 10.0)}


def phi(r, node):
    """A smooth mode-shape value at a node (any symmetric modal model will do)."""
    x, y = NODES[node]
    return np.cos((r + 1) * np.pi * x / 80.0) * np.cos(r * np.pi * y / 50.0) + 0.1 * (r + 1)


def mobility(j, k):
    w = 2 * np.pi * FREQ_HZ
    h = np.zeros_like(w, dtype=complex)
    for r, (fr, z) in enumerate(MODES):
        wr = 2 * np.pi * fr
        h += 1j * w * phi(r, j) * phi(r, k) / (wr**2 - w**2 + 2j * z * wr * w)
    return h


# numerator specific data type, length exponent, unit label, and the factor (i w)^p from mobility
KINDS = {
    "acceleration": (12, 1, "m/s^2/N", 1),
    "velocity": (11, 1, "m/s/N", 0),
    "displacement": (8, 1, "m/N", -1),
}


def record(kind, rsp, ref):
    spec, lexp, units, p = KINDS[kind]
    w = 2 * np.pi * FREQ_HZ
    data = mobility(rsp, ref) * (1j * w) ** p if p >= 0 else np.zeros(len(w), dtype=complex)
    if p < 0:
        nz = w > 0
        data[nz] = mobility(rsp, ref)[nz] / (1j * w[nz])
    return pyuff.prepare_58(
        binary=0, id1="hbmu few-point fixture", id2="B-01 free", id3="NONE", id4="NONE",
        id5="NONE", func_type=4, ver_num=0, load_case_id=0, rsp_ent_name="BOARD",
        rsp_node=rsp, rsp_dir=3, ref_ent_name="HAMMER", ref_node=ref, ref_dir=3,
        ord_data_type=6, num_pts=len(data), abscissa_spacing=1, abscissa_min=FREQ_HZ[0],
        abscissa_inc=FREQ_HZ[1] - FREQ_HZ[0], z_axis_value=0.0, abscissa_spec_data_type=18,
        abscissa_len_unit_exp=0, abscissa_force_unit_exp=0, abscissa_temp_unit_exp=0,
        abscissa_axis_units_lab="Hz", ordinate_spec_data_type=spec,
        ordinate_len_unit_exp=lexp, ordinate_force_unit_exp=0, ordinate_temp_unit_exp=0,
        ordinate_axis_units_lab=units, orddenom_spec_data_type=13, orddenom_len_unit_exp=0,
        orddenom_force_unit_exp=1, orddenom_temp_unit_exp=0, orddenom_axis_units_lab="N",
        z_axis_spec_data_type=0, z_axis_len_unit_exp=0, z_axis_force_unit_exp=0,
        z_axis_temp_unit_exp=0, z_axis_axis_units_lab="NONE", data=data, x=FREQ_HZ,
    )


MEASUREMENTS = {
    "M1": [("acceleration", rsp, 4) for rsp in (1, 2, 3)],
    "M2": [("acceleration", 1, ref) for ref in (1, 2, 3, 4, 5)],
    "M3": [("displacement", rsp, 4) for rsp in (2, 5)],
}


# M4's modes: (frequency Hz, damping ratio, complex factor of the shape; None = a normal mode)
VENDOR = [(410.0, 0.012, None), (980.0, 0.009, 0.6 - 0.8j)]


def mode_sets():
    ids = np.array(sorted(NODES))
    out = []
    for r, (fr, z, factor) in enumerate(VENDOR):
        shape = np.array([phi(r, n) for n in ids])
        zeros = np.zeros(len(ids))
        common = dict(model_type=1, id1="NONE", id2="NONE", id3="NONE", id4="NONE", id5="NONE",
                      data_ch=2, spec_data_type=8, n_data_per_node=3, node_nums=ids,
                      load_case=1, mode_n=r + 1)
        if factor is None:
            out.append(pyuff.prepare_55(analysis_type=2, data_type=2, r1=zeros, r2=zeros,
                                        r3=shape, freq=fr, modal_m=0.0, modal_damp_vis=z,
                                        modal_damp_his=0.0, **common))
        else:
            wn = 2 * np.pi * fr
            eig = -z * wn + 1j * wn * np.sqrt(1 - z * z)
            out.append(pyuff.prepare_55(analysis_type=3, data_type=5, r1=zeros + 0j,
                                        r2=zeros + 0j, r3=shape * factor, eig=eig,
                                        modal_a=0j, modal_b=0j, **common))
    return out


def write(camp):
    os.makedirs(os.path.join(camp, "vibrometer"), exist_ok=True)
    os.makedirs(os.path.join(camp, "scale"), exist_ok=True)
    rows = ["measurement_id,board_id,setup,file,notes"]
    for mid, recs in MEASUREMENTS.items():
        path = os.path.join(camp, "vibrometer", f"{mid}.uff")
        if os.path.exists(path):
            os.remove(path)
        u = pyuff.UFF(path)
        ids = sorted(NODES)
        u.write_sets(pyuff.prepare_2411(
            node_nums=np.array(ids), def_cs=np.zeros(len(ids), int),
            disp_cs=np.zeros(len(ids), int), color=np.full(len(ids), 11), x=np.array([NODES[i][0] for i in ids]),
            y=np.array([NODES[i][1] for i in ids]), z=np.zeros(len(ids))), mode="add")
        for kind, rsp, ref in recs:
            u.write_sets(record(kind, rsp, ref), mode="add")
        rows.append(f"{mid},B-01,free,vibrometer/{mid}.uff,few-point hammer test")
    path = os.path.join(camp, "vibrometer", "M4.uff")
    if os.path.exists(path):
        os.remove(path)
    u = pyuff.UFF(path)
    ids = sorted(NODES)
    u.write_sets(pyuff.prepare_2411(
        node_nums=np.array(ids), def_cs=np.zeros(len(ids), int),
        disp_cs=np.zeros(len(ids), int), color=np.full(len(ids), 11),
        x=np.array([NODES[i][0] for i in ids]), y=np.array([NODES[i][1] for i in ids]),
        z=np.zeros(len(ids))), mode="add")
    u.write_sets(mode_sets(), mode="add")
    rows.append("M4,B-01,free,vibrometer/M4.uff,modes from the lab's modal software")
    with open(os.path.join(camp, "campaign.csv"), "w") as f:
        f.write("\n".join(rows) + "\n")
    with open(os.path.join(camp, "scale", "balance.log"), "w") as f:
        f.write("2026-11-01T08:00:00 B-01 S S 13.0312 g\n")


def check(camp, out):
    import pandas as pd

    frf = pd.read_parquet(os.path.join(out, "frf.parquet"))
    frf = frf[frf.function_type == 4]
    written = {(mid, rsp if mid != "M2" else ref, ref if mid != "M2" else rsp): kind
               for mid, recs in MEASUREMENTS.items() for kind, rsp, ref in recs}
    got = {}
    worst = 0.0
    for r in frf.itertuples():
        key = (r.measurement_id, int(r.node), int(r.reference_node))
        got[key] = r.measured_as
        y = mobility(int(r.node), int(r.reference_node))
        h = np.asarray(r.re) + 1j * np.asarray(r.im)
        f = r.freq_start_hz + r.freq_step_hz * np.arange(r.n_lines)
        assert np.allclose(f, FREQ_HZ), key
        nz = f > 0  # an accelerance has no mobility at 0 Hz
        err = np.max(np.abs(h[nz] - y[nz])) / np.max(np.abs(y))
        worst = max(worst, float(err))
        assert r.measured_as == f"{written[key]}/force", (key, r.measured_as)
    assert set(got) == set(written), (sorted(got), sorted(written))
    print(json.dumps({"records": len(got), "worst_rel_error": worst}))
    assert worst < 1e-9, worst


def check_modes(out):
    import pandas as pd

    modes = pd.read_parquet(os.path.join(out, "modes.parquet"))
    assert set(modes[modes.source == "uff55"].measurement_id) == {"M4"}, modes.source
    m4 = modes[modes.measurement_id == "M4"].sort_values("mode")
    assert len(m4) == len(VENDOR), m4
    worst_f = worst_shape = 0.0
    for row, (fr, z, _) in zip(m4.itertuples(), VENDOR):
        r = row.mode - 1
        want = np.array([phi(r, int(n)) for n in row.node])
        want = want / want[np.argmax(np.abs(want))]
        worst_shape = max(worst_shape, float(np.max(np.abs(np.asarray(row.shape) - want))))
        worst_f = max(worst_f, abs(row.freq_hz - fr) / fr, abs(row.damping_ratio - z) / z)
        assert abs(row.mpc - 1.0) < 1e-9, row.mpc
        assert row.cluster_size == 0 and np.isnan(row.fit_error), row
    print(json.dumps({"modes": len(m4), "worst_rel_freq_damping": worst_f,
                      "worst_shape": worst_shape}))
    # pyuff writes E13.5: five significant digits
    assert worst_f < 1e-5 and worst_shape < 1e-4, (worst_f, worst_shape)


if __name__ == "__main__":
    if sys.argv[1] == "write":
        write(sys.argv[2])
    elif sys.argv[1] == "check-modes":
        check_modes(sys.argv[2])
    else:
        check(sys.argv[2], sys.argv[3])
