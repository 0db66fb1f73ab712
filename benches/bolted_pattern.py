#!/usr/bin/env python3
"""Does the bolted comparison show the misfit pattern its scenario implies? (issue 10)

A virtual-lab campaign's truth.json states, per concealed effect, how much each bolted mode
moves against a model without the effect (`expected_diagnosis.modes[].mean_shift_percent`).
The updating cannot show that shift as it is: step 2 fits each measurement's contact
stiffness K_con, which takes up the part of the shift along K_con's sensitivity. What the
bolted residuals should show is the rest: the shift minus its least-squares projection on
the modes' K_con sensitivities (%/%, `hbmu fe sensitivity --setup bolted`), fitted over
the modes step 2 updated. This script prints, per bolted label, the shift, the implied
misfit and the mean relative residual of step 2 (update_joints/residuals.parquet, each
measurement at its own K_con), then their correlation and the RMS of their difference,
both after removing the mean over labels (a common offset is the board parameters' and K's
business, not the pattern's).

Labels are matched to the truth's modes by the nearest frequency. The linear projection is
an approximation (the sensitivity at the board file's nominal K_con, not at the fitted
one): the pattern is compared, not the values.

Usage: benches/bolted_pattern.py WORK [HBMU]   (WORK: a work directory of a lab scenario,
e.g. target/work/paper after `make -C pipelines demo`; HBMU: the binary, default
target/debug/hbmu)
"""
import json
import subprocess
import sys
import tempfile

import numpy as np
import pandas as pd


def main():
    work = sys.argv[1]
    hbmu = sys.argv[2] if len(sys.argv) > 2 else "target/debug/hbmu"
    truth = json.load(open(f"{work}/truth.json"))
    shifts = {}
    for e in truth["effects"]:
        ed = e.get("expected_diagnosis") or {}
        for m in ed.get("modes", []):
            if m["setup"] == "bolted":
                shifts.setdefault(m["mode"], [m["freq_hz"], 0.0])
                shifts[m["mode"]][1] += m["mean_shift_percent"]
    if not shifts:
        print("no bolted shift in truth.json: the scenario implies no bolted pattern")
        return
    with tempfile.TemporaryDirectory() as tmp:
        out = f"{tmp}/sens.parquet"
        subprocess.run([hbmu, "fe", "sensitivity", "--setup", "bolted", "--n-modes",
                        str(max(shifts) + 2), "--out", out], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        sens = pd.read_parquet(out)
    s_k = sens[sens.param == "k_con_n_per_m"].set_index("mode").pct_per_pct
    res = pd.read_parquet(f"{work}/update_joints/residuals.parquet")
    res = res[res.setup == "bolted"]
    by = res.groupby("label").agg(freq_hz=("freq_hz", "mean"),
                                  residual_pct=("rel_residual", lambda v: 100 * v.mean()),
                                  updated=("used_for_updating", "max"),
                                  n=("rel_residual", "size"))
    rows = []
    for label, r in by.iterrows():
        mode = min(shifts, key=lambda m: abs(shifts[m][0] - r.freq_hz))
        rows.append(dict(label=label, mode=mode, shift_pct=shifts[mode][1],
                         s_k=s_k.get(mode, np.nan), residual_pct=r.residual_pct,
                         updated=bool(r.updated), n=int(r.n)))
    t = pd.DataFrame(rows).sort_values("mode")
    fit = t[t.updated]
    alpha = float((fit.shift_pct * fit.s_k).sum() / (fit.s_k ** 2).sum())
    t["implied_misfit_pct"] = t.shift_pct - alpha * t.s_k
    print(f"K_con taken up by step 2 (least squares over the updated labels): "
          f"{alpha:.1f} % (shift = that x the %/% sensitivity)")
    print(t.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    a = t.implied_misfit_pct - t.implied_misfit_pct.mean()
    b = t.residual_pct - t.residual_pct.mean()
    corr = float(np.corrcoef(a, b)[0, 1])
    rms = float(np.sqrt(((a - b) ** 2).mean()))
    spread = float(np.sqrt((a ** 2).mean()))
    print(f"pattern (mean over labels removed): correlation {corr:.2f}, RMS difference "
          f"{rms:.3f} % against an implied spread of {spread:.3f} % "
          f"({'shows' if corr >= 0.7 else 'does NOT show'} the pattern: correlation >= 0.7)")


if __name__ == "__main__":
    main()
