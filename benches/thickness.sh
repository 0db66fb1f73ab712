#!/usr/bin/env bash
# Issue 53's measured specimens: a campaign whose boards differ in FR-4 core thickness
# (benches/scenarios/thickness.toml: the null campaign on the plate truth, core thickness
# h0 (1 + 0.045 z) per board, -5.8 % to +8.3 % at its seed), once with each board's
# thickness on the sheet (the model takes it as known) and once without
# (thickness_nosheet.toml: the same files, the sheet without the columns). Runs the DAG
# (with the sheet: every stage to the report; without: up to step 1) and prints per board
# and modulus the posterior mean's error against the truth, its 90 % interval's verdict, and
# per modulus the mean error over the boards and its correlation with the board's thickness
# deviation: without the thickness the moduli absorb it (bias), with it they should not.
#
# Usage: benches/thickness.sh   (work dirs target/work/thickness, target/work/thickness_nosheet)
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
hbmu=${HBMU:-$root/target/debug/hbmu}
run() { # scenario targets...
  local s=$1; shift
  local w=$root/target/work/$s
  local t0=$(date +%s)
  make -C "$root/pipelines" --no-print-directory "$@" SCENARIO="$root/benches/scenarios/$s.toml" \
    WORK="$w" HBMU="$hbmu" > "$w.log" 2>&1 || { echo "$s: pipeline failed, see $w.log"; exit 1; }
  echo "$s: $* in $(( $(date +%s) - t0 )) s"
}
run thickness all
run thickness_nosheet prepare update-boards
python3 - "$root/target/work" <<'PY'
import json, sys
import numpy as np
import pandas as pd
base = sys.argv[1]
for name in ["thickness", "thickness_nosheet"]:
    w = f"{base}/{name}"
    truth = json.load(open(f"{w}/truth.json"))
    s = pd.read_parquet(f"{w}/update_boards/summary.parquet")
    b = s[s.board_id.notna() & s.measurement_id.isna()]
    print(f"== {name}")
    rows = []
    for x in truth["boards"]:
        for p in ["e_x_pa", "e_y_pa", "g_xy_pa", "mass_scale"]:
            r = b[(b.board_id == x["board_id"]) & (b.parameter == p)]
            if len(r) != 1:
                continue
            r = r.iloc[0]
            rows.append(dict(board=x["board_id"], param=p, h_mm=1e3 * x["core_thickness_m"],
                             err_pct=100 * (r["mean"] / x[p] - 1),
                             inside=bool(r.q05 <= x[p] <= r.q95),
                             half_width_pct=50 * (r.q95 - r.q05) / r["mean"]))
    t = pd.DataFrame(rows)
    h = t.groupby("board").h_mm.first()
    for p, g in t.groupby("param", sort=False):
        g = g.set_index("board")
        c = np.corrcoef(g.err_pct, h[g.index])[0, 1]
        print(f"  {p:11s} error {g.err_pct.mean():+7.3f} % mean, {g.err_pct.abs().max():6.3f} % worst, "
              f"corr with thickness {c:+.2f}; inside 90 % {int(g.inside.sum())}/{len(g)}; "
              f"half-width {g.half_width_pct.median():.3f} % (median)")
    print("  per board (error %):")
    print(t.pivot(index="board", columns="param", values="err_pct").join(h).round(3).to_string())
PY
# The population means against the truth's (benches/recovery.py).
for s in thickness thickness_nosheet; do
  python3 "$root/benches/recovery.py" "$root/target/work/$s" | grep -E "inside 90 %|    mu_|Table-2"
done
