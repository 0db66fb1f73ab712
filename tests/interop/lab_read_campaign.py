"""Read a virtual-lab campaign with third-party readers: the sheet with pandas, every UFF
named by the sheet with pyuff. Prints one JSON summary on stdout for the Rust test
(src/lab/tests.rs) to compare with the truth.

Usage: python3 lab_read_campaign.py CAMPAIGN_DIR
"""
import json
import os
import sys

import numpy as np
import pandas as pd
import pyuff


def main(campaign):
    sheet = pd.read_csv(os.path.join(campaign, "campaign.csv"), dtype=str, keep_default_na=False)
    out = {"columns": list(sheet.columns), "rows": [], "files": {}}
    for _, row in sheet.iterrows():
        out["rows"].append({k: row[k] for k in sheet.columns})
        path = os.path.join(campaign, row["file"])
        uff = pyuff.UFF(path)
        sets = uff.read_sets()
        if isinstance(sets, dict):
            sets = [sets]
        summary = {"types": [int(s["type"]) for s in sets], "nodes": {}, "records": [], "units": None}
        for s in sets:
            t = int(s["type"])
            if t == 164:
                summary["units"] = {"length": float(s["length"]), "force": float(s["force"])}
            elif t in (2411, 15):
                for i, n in enumerate(s["node_nums"]):
                    summary["nodes"][str(int(n))] = [float(s["x"][i]), float(s["y"][i]), float(s["z"][i])]
            elif t == 58:
                x = np.asarray(s["x"], dtype=float)
                y = np.asarray(s["data"])
                summary["records"].append({
                    "func_type": int(s["func_type"]),
                    "rsp_node": int(s["rsp_node"]),
                    "rsp_dir": int(s["rsp_dir"]),
                    "ref_node": int(s["ref_node"]),
                    "ref_dir": int(s["ref_dir"]),
                    "num_pts": int(s["num_pts"]),
                    "x0": float(x[0]),
                    "dx": float(x[1] - x[0]),
                    "complex": bool(np.iscomplexobj(y)),
                    # |y| summed over lines: compared with our own reader of the same file
                    "abs_sum": float(np.sum(np.abs(y))),
                })
        out["files"][row["file"]] = summary
    json.dump(out, sys.stdout)


if __name__ == "__main__":
    main(sys.argv[1])
