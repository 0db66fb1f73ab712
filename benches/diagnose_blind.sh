#!/usr/bin/env bash
# Blind discovery: each concealed-effect scenario of the virtual lab (data/lab/<name>.toml)
# through the whole DAG up to `diagnose`, which is told nothing about the scenario. Afterwards,
# and only then, this script reads the lab's truth.json (kept outside the campaign) and scores
# the diagnosis against the issue's acceptance: the right mechanism first, its joint /
# location (within 10 mm) / covariate, a 90 % interval that covers the true parameter, and a
# held-out mean absolute frequency error at least 2x smaller.
#
# Usage: benches/diagnose_blind.sh [SCENARIO...]   (a built-in name, a scenario file such as
# benches/scenarios/mass_and_temperature.toml, or a work directory with a generated campaign/
# and its truth.json; default: the five effect scenarios and underfill, the effect kept out
# of the library)
# Env: REFITS (candidate refits per diagnosis, default 3). Work dirs: target/work/blind-<name>.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
scen=("$@")
if [ ${#scen[@]} -eq 0 ]; then scen=(rotational loose_bolt temperature lumped_mass fixture underfill); fi
refits=${REFITS:-3}
for s in "${scen[@]}"; do
  # A built-in name (data/lab/<name>.toml), a scenario file's path, or a directory holding a
  # campaign the lab wrote before (campaign/ and truth.json, e.g. a solid-truth campaign,
  # whose generation takes minutes): then the DAG runs on the campaign as a user's would
  # (CAMPAIGN=, no lab stage) and the wall time is the analysis alone.
  if [ -d "$s" ] && [ -f "$s/truth.json" ] && [ -d "$s/campaign" ]; then
    given=$(cd "$s" && pwd); s=$(basename "$given"); s=${s#reproof-}
    work=$root/target/work/blind-$s
    mkdir -p "$work"
    cp "$given/truth.json" "$work/truth.json"
    input=(CAMPAIGN="$given/campaign")
  else
    src=$root/data/lab/$s.toml
    if [ -f "$s" ]; then src=$s; s=$(basename "$s" .toml); fi
    work=$root/target/work/blind-$s
    mkdir -p "$work"
    cp "$src" "$work/scenario.toml"
    input=(SCENARIO="$work/scenario.toml")
  fi
  start=$(date +%s)
  make -C "$root/pipelines" --no-print-directory all update-boards update-joints diagnose \
    "${input[@]}" WORK="$work" DIAGNOSE_REFITS="$refits" > "$work/make.log" 2>&1 || {
    echo "$s: pipeline failed (see $work/make.log)"; tail -5 "$work/make.log"; continue; }
  python3 "$root/benches/score_diagnosis.py" "$work" "$s" "$(( $(date +%s) - start ))"
done
