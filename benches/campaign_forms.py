#!/usr/bin/env python3
"""A scanning-vibrometer campaign turned into the forms other labs hand over (issue 53), written
with the third-party pyuff, so that the updating can be compared on the same boards.

Usage:
  campaign_forms.py FORM SRC_CAMPAIGN DST_CAMPAIGN [MODES_PARQUET]

FORM:
  one-point    one response per measurement: the scan point farthest from the excitation
               reference (a transfer FRF between opposite corners), with its coherence; for a
               base-excited (bolted) measurement, which has no reference point on the board,
               the point that moves most (largest mean |H|², where a lab would put the
               accelerometer; the corner opposite a corner is next to a bolt there);
  three-point  three responses: that point and two more, each the farthest from those chosen
               (farthest-point sampling), as three accelerometers would be placed;
  roving       free-free measurements as a roving hammer: the accelerometer at the old
               reference, the hammer at nine points (farthest-point sampling); by
               reciprocity H(ref, j) = H(j, ref), so the records are the scan's at those
               points with response and reference swapped. A base-excited (bolted) record
               cannot rove: bolted measurements become one-point;
  modes55      no FRF: each measurement's modes as a modal-analysis program exports them
               (dataset 55, normal modes, X/Y/Z translations with Z the shape), taken from
               MODES_PARQUET (extract's modes.parquet of the full scan: the vendor's
               identification is played by hbmu's own, so this form tests the 55 path and the
               pairing, not another identification method).
The sheet and the balance logs are copied unchanged; geometry (2411) keeps the nodes used.
pyuff writes no transmissibility (function type 5: its writer refuses it), so a bolted
measurement's chosen records are copied as the source file's own text.
"""
import os
import shutil
import sys

import numpy as np
import pyuff


def farthest_points(xy, start, k):
    """Indices of k points: each the farthest from `start` and those already chosen."""
    chosen = []
    d = np.linalg.norm(xy - xy[start], axis=1)
    for _ in range(k):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(xy - xy[i], axis=1))
    return chosen


def raw_58(path):
    """The bytes of each dataset 58 (ASCII or binary 58b) of type 5 in a UFF file, by response
    node: opening -1 to closing -1, a 58b's binary part skipped by its header's byte count."""
    with open(path, "rb") as fh:
        data = fh.read()
    n = len(data)

    def line_at(p):
        e = data.find(b"\n", p)
        e = n if e < 0 else e
        return data[p:e], e + 1

    out, pos = {}, 0
    while pos < n:
        line, nxt = line_at(pos)
        if line.strip() != b"-1":
            pos = nxt
            continue
        start = pos
        head, cur = line_at(nxt)
        tok = head.split()
        if not tok or tok[0] not in (b"58", b"58b"):
            # another dataset: skip to its closing -1
            while cur < n:
                line, cur = line_at(cur)
                if line.strip() == b"-1":
                    break
            pos = cur
            continue
        nascii, nbytes = (int(tok[3]), int(tok[4])) if tok[0] == b"58b" else (11, 0)
        lines = []
        for _ in range(nascii):
            line, cur = line_at(cur)
            lines.append(line)
        cur += nbytes
        while cur < n:
            line, cur = line_at(cur)
            if line.strip() == b"-1":
                break
        rec6 = lines[5].split() if len(lines) > 5 else []
        if rec6 and rec6[0] == b"5":
            out[int(rec6[5])] = data[start:cur]
        pos = cur
    return out


def geometry(sets):
    g = next(s for s in sets if s["type"] in (2411, 15))
    return {int(n): (x, y, z) for n, x, y, z in zip(g["node_nums"], g["x"], g["y"], g["z"])}


def geometry_set(nodes, keep):
    ids = sorted(set(keep))
    return pyuff.prepare_2411(
        node_nums=np.array(ids), def_cs=np.ones(len(ids), int), disp_cs=np.ones(len(ids), int),
        color=np.full(len(ids), 11), x=np.array([nodes[i][0] for i in ids]),
        y=np.array([nodes[i][1] for i in ids]), z=np.array([nodes[i][2] for i in ids]))


def convert(form, sets, modes, raw):
    nodes = geometry(sets)
    head = [s for s in sets if s["type"] in (151, 164)]
    recs = [s for s in sets if s["type"] == 58]
    resp = [r for r in recs if r["func_type"] != 6]
    coh = {int(r["rsp_node"]): r for r in recs if r["func_type"] == 6}
    if form == "modes55":
        if modes is None or modes.empty:
            raise SystemExit("modes55: no modes for this measurement in MODES_PARQUET")
        keep = [int(n) for n in modes.iloc[0].node]
        out = head + [geometry_set(nodes, keep)]
        for k, m in enumerate(modes.itertuples()):
            z = np.nan_to_num(np.asarray(m.shape, float))
            zeros = np.zeros(len(z))
            out.append(pyuff.prepare_55(
                model_type=1, id1="NONE", id2="NONE", id3="NONE", id4="NONE", id5="NONE",
                analysis_type=2, data_ch=2, spec_data_type=8, data_type=2, n_data_per_node=3,
                node_nums=np.array([int(n) for n in m.node]), r1=zeros, r2=zeros, r3=z,
                load_case=1, mode_n=k + 1, freq=float(m.freq_hz), modal_m=0.0,
                modal_damp_vis=float(m.damping_ratio), modal_damp_his=0.0))
        return out, b""
    ref = int(resp[0]["ref_node"])
    base_excited = resp[0]["func_type"] == 5
    by_node = {int(r["rsp_node"]): r for r in resp}
    ids = sorted(by_node)
    xy = np.array([nodes[i][:2] for i in ids])
    ref_xy = np.array(nodes.get(ref, (0.0, 0.0, 0.0))[:2])
    start = int(np.argmin(np.linalg.norm(xy - ref_xy, axis=1)))
    if base_excited:
        power = [float(np.mean(np.abs(by_node[i]["data"]) ** 2)) for i in ids]
        first = int(np.argmax(power))
        rest = [ids[i] for i in farthest_points(xy, first, 2)] if form == "three-point" else []
        chosen = [ids[first]] + rest
        out = head + [geometry_set(nodes, chosen)]
        text = b"".join(raw[n] for n in chosen)
        out += [coh[n] for n in chosen if n in coh]
        return out, text
    if form == "roving" and not base_excited and ref in by_node:
        hammer = [ids[i] for i in farthest_points(xy, start, 9)]
        out = head + [geometry_set(nodes, hammer + [ref])]
        for j in hammer:
            r = dict(by_node[j])
            r["rsp_node"], r["ref_node"] = ref, j
            out.append(r)
        return out, b""
    k = 3 if form == "three-point" else 1
    chosen = [ids[i] for i in farthest_points(xy, start, k)]
    out = head + [geometry_set(nodes, chosen + ([ref] if ref in nodes else []))]
    text = b""
    for n in chosen:
        if base_excited:
            text += raw[n]
        else:
            out.append(by_node[n])
        if n in coh:
            out.append(coh[n])
    return out, text


def main():
    form, src, dst = sys.argv[1], sys.argv[2], sys.argv[3]
    modes = None
    if form == "modes55":
        import pandas as pd

        modes = pd.read_parquet(sys.argv[4])
    import csv

    with open(os.path.join(src, "campaign.csv"), newline="") as fh:
        file_to_id = {os.path.normpath(r["file"]): r["measurement_id"] for r in csv.DictReader(fh)}
    if os.path.exists(dst):
        shutil.rmtree(dst)
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.uff"))
    for root, _, files in os.walk(src):
        for f in files:
            if not f.endswith(".uff"):
                continue
            rel = os.path.relpath(os.path.join(root, f), src)
            try:
                sets = pyuff.UFF(os.path.join(src, rel)).read_sets()
            except Exception as e:  # a file the lab wrote broken stays broken
                print(f"{rel}: pyuff cannot read it ({e}); copied as it is", file=sys.stderr)
                shutil.copy(os.path.join(src, rel), os.path.join(dst, rel))
                continue
            sets = sets if isinstance(sets, list) else [sets]
            mine = None
            if modes is not None:
                mid = file_to_id.get(os.path.normpath(rel), os.path.splitext(f)[0])
                mine = modes[modes.measurement_id == mid].sort_values("mode")
                if mine.empty:
                    # A measurement the full scan had no modes for (quarantined there) stays
                    # as it was, so that the form's ingest reports it the same way.
                    shutil.copy(os.path.join(src, rel), os.path.join(dst, rel))
                    continue
            out, text = convert(form, sets, mine, raw_58(os.path.join(src, rel)))
            path = os.path.join(dst, rel)
            os.remove(path) if os.path.exists(path) else None
            pyuff.UFF(path).write_sets(out, mode="add")
            with open(path, "ab") as fh:
                fh.write(text)


if __name__ == "__main__":
    main()
