#!/usr/bin/env bash
# Issue 53's acceptance: a virtual-lab campaign as the scanning vibrometer recorded it (the
# full scan) and turned into the forms other labs hand over (benches/campaign_forms.py:
# one-point, three-point, roving hammer, 55-only), each through the DAG up to step 1 at its
# defaults. Prints per form: pairs accepted and the modes used, the truth's board parameters
# inside their 90 % intervals (benches/recovery.py), and the median 90 % interval width of
# each board parameter relative to its median, against the full scan's.
#
# Usage: benches/forms.sh [SCENARIO_WORK_DIR]   (a work directory holding campaign/ and
# truth.json, e.g. one the lab wrote; default: the realistic_paper scenario, generated into
# target/work/forms-lab). Work dirs: target/work/forms-<form>.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
hbmu=${HBMU:-$root/target/debug/hbmu}
src=${1:-}
if [ -z "$src" ]; then
  src=$root/target/work/forms-lab
  make -C "$root/pipelines" --no-print-directory lab SCENARIO=realistic_paper WORK="$src" HBMU="$hbmu" > /dev/null
fi
run() { # form campaign
  local w=$root/target/work/forms-$1
  # A fresh directory: make judges by timestamps, and a campaign older than the last run's
  # outputs (another source) would be taken as up to date.
  rm -rf "$w"
  mkdir -p "$w"
  cp "$src/truth.json" "$w/truth.json"
  local t0=$(date +%s)
  make -C "$root/pipelines" --no-print-directory prepare update-boards CAMPAIGN="$2" WORK="$w" HBMU="$hbmu" > "$w.log" 2>&1 \
    || { echo "$1: pipeline failed, see $w.log"; return; }
  echo "$1: $(( $(date +%s) - t0 )) s; $(grep -h '^pair:' "$w.log" | tail -1)"
}
run full "$src/campaign"
for form in one-point three-point roving modes55; do
  c=$root/target/work/forms-campaign-$form
  python3 "$root/benches/campaign_forms.py" "$form" "$src/campaign" "$c" \
    "$root/target/work/forms-full/extract/modes.parquet"
  run "$form" "$c"
done
python3 - "$root/target/work" <<'PY'
import subprocess, sys
import pandas as pd
base = sys.argv[1]
forms = ["full", "one-point", "three-point", "roving", "modes55"]
width = {}
for f in forms:
    w = f"{base}/forms-{f}"
    try:
        s = pd.read_parquet(f"{w}/update_boards/summary.parquet")
    except Exception as e:
        print(f"{f}: no step 1 ({e})")
        continue
    b = s[s.board_id.notna()]
    width[f] = ((b.q95 - b.q05) / b.q50.abs()).groupby(b.parameter).median()
    used = pd.read_parquet(f"{w}/pair/presence.parquet")
    used = used[used.used_for_updating].groupby("setup").label.apply(list).to_dict()
    print(f"== {f}: modes used for updating {used}")
    out = subprocess.run(["python3", f"{base}/../../benches/recovery.py", w], capture_output=True, text=True).stdout
    print("\n".join(l for l in out.splitlines()
                    if "inside 90 %" in l or l.strip().startswith(("board:", "mu:", "sigma:"))))
if "full" in width:
    print("median 90 % width of the board parameters, relative to the full scan's:")
    t = pd.DataFrame(width)
    print((t.div(t["full"], axis=0)).round(2).to_string())
    print("absolute (relative to the median):")
    print(t.round(4).to_string())
PY
