#!/usr/bin/env python3
"""Read a UFF file written by hbmu with the third-party package pyuff and compare it, value for
value, with a JSON description of what hbmu meant to write.

Usage: pyuff_read_check.py FILE.uff EXPECTED.json

EXPECTED.json: {"datasets": [ {...}, ... ]} in file order, each with "type" and, per type:
  58:   func_type, ord_data_type, binary, num_pts, rsp_node, rsp_dir, ref_node, ref_dir,
        id1, x (all abscissa values), re, im (im absent for real data), rel_tol, x_rel_tol
  2411/15: node_nums, x, y, z, rel_tol
  164:  units_code, description, temp_mode, length, force, temp, temp_offset, rel_tol
A value v read by pyuff matches the expected e if |v - e| <= rel_tol * max(|e|, scale), where
scale is the largest magnitude of the array (printed E fields carry relative precision).
Exits 0 and prints "OK <n> datasets" when everything matches, else prints each mismatch and
exits 1.
"""
import json
import sys

import numpy as np
import pyuff


def close(name, got, exp, tol, errors, scale=None):
    got = np.asarray(got, dtype=float)
    exp = np.asarray(exp, dtype=float)
    if got.shape != exp.shape:
        errors.append(f"{name}: expected shape {exp.shape}, found {got.shape}")
        return
    if exp.size == 0:
        return
    s = np.max(np.abs(exp)) if scale is None else scale
    bound = tol * np.maximum(np.abs(exp), 1e-300) + tol * 1e-6 * s
    bad = np.nonzero(np.abs(got - exp) > bound)[0]
    if bad.size:
        i = int(bad[0])
        errors.append(f"{name}[{i}]: expected {exp.flat[i]!r}, found {got.flat[i]!r} "
                      f"({bad.size} values off, rel_tol {tol})")


def main():
    path, exp_path = sys.argv[1], sys.argv[2]
    with open(exp_path) as fh:
        expected = json.load(fh)["datasets"]
    sets = pyuff.UFF(path).read_sets()
    if isinstance(sets, dict):
        sets = [sets]
    errors = []
    if len(sets) != len(expected):
        errors.append(f"dataset count: expected {len(expected)}, found {len(sets)}")
    for k, (d, e) in enumerate(zip(sets, expected)):
        tag = f"dataset #{k} ({e['type']})"
        if int(d["type"]) != e["type"]:
            errors.append(f"{tag}: type: expected {e['type']}, found {d['type']}")
            continue
        tol = e.get("rel_tol", 0.0)
        if e["type"] == 58:
            for key in ["func_type", "ord_data_type", "binary", "num_pts", "rsp_node", "rsp_dir",
                        "ref_node", "ref_dir"]:
                if int(d[key]) != e[key]:
                    errors.append(f"{tag}: {key}: expected {e[key]}, found {d[key]}")
            if d["id1"].strip() != e["id1"]:
                errors.append(f"{tag}: id1: expected {e['id1']!r}, found {d['id1']!r}")
            close(f"{tag} x", d["x"], e["x"], e.get("x_rel_tol", tol), errors)
            data = np.asarray(d["data"])
            close(f"{tag} re", data.real, e["re"], tol, errors)
            if "im" in e:
                if not np.iscomplexobj(data):
                    errors.append(f"{tag}: expected complex data, found real")
                else:
                    close(f"{tag} im", data.imag, e["im"], tol, errors)
        elif e["type"] in (2411, 15):
            close(f"{tag} node_nums", d["node_nums"], e["node_nums"], 0.0, errors)
            for c in "xyz":
                close(f"{tag} {c}", d[c], e[c], tol, errors)
        elif e["type"] == 164:
            for key in ["units_code", "temp_mode"]:
                if int(d[key]) != e[key]:
                    errors.append(f"{tag}: {key}: expected {e[key]}, found {d[key]}")
            if d["units_description"].strip() != e["description"]:
                errors.append(f"{tag}: description: expected {e['description']!r}, "
                              f"found {d['units_description']!r}")
            for key in ["length", "force", "temp", "temp_offset"]:
                close(f"{tag} {key}", [d[key]], [e[key]], tol, errors)
    if errors:
        print("\n".join(errors))
        sys.exit(1)
    print(f"OK {len(sets)} datasets")


if __name__ == "__main__":
    main()
