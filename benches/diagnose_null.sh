#!/usr/bin/env bash
# The diagnosis's false-alarm check: the lab's null scenario (data/lab/null.toml: no concealed
# effect) under several seeds, each through the whole DAG up to `diagnose`; prints each seed's
# verdict, what it located and its wall time. A correct diagnosis says no_missing_physics on
# every seed. Usage: benches/diagnose_null.sh SEED... (default 5 seeds); work directories
# under target/work/null-<seed>. Run from anywhere; needs the pipeline's make.
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
seeds=("$@")
if [ ${#seeds[@]} -eq 0 ]; then seeds=(1 2 3 4 5); fi
for s in "${seeds[@]}"; do
  work=$root/target/work/null-$s
  mkdir -p "$work"
  sed -E "s/^seed = .*/seed = $s/; s/^name = .*/name = \"null-$s\"/" "$root/data/lab/null.toml" > "$work/scenario.toml"
  start=$(date +%s)
  make -C "$root/pipelines" --no-print-directory all update-boards update-joints diagnose \
    SCENARIO="$work/scenario.toml" WORK="$work" > "$work/make.log" 2>&1 || {
    echo "seed $s: pipeline failed (see $work/make.log)"; tail -5 "$work/make.log"; continue; }
  python3 - "$work" "$s" "$(( $(date +%s) - start ))" <<'PY'
import json, sys
work, seed, secs = sys.argv[1], sys.argv[2], sys.argv[3]
d = json.load(open(f"{work}/diagnose/diagnosis.json"))
t = json.load(open(f"{work}/truth.json"))
loc = d["located"]
modes = ", ".join(f"{m['setup']}/{m['label']} {100 * m['mean_rel_residual']:+.3f} % ({'+'.join(m['reasons'])})" for m in loc["modes"])
cands = ", ".join(f"{c['id']} ln B {c['refit']['log_bayes_factor']:.1f}" for c in d["candidates"] if c.get("refit") and c["refit"].get("log_bayes_factor") is not None)
mis = max(abs(x) for x in t["model_misfit"]["bolted_misfit_percent"] + t["model_misfit"]["free_misfit_percent"])
print(f"seed {seed}: {d['verdict']} in {secs} s; truth model misfit max {mis:.3f} %; "
      f"located modes [{modes}] measurements {loc['measurements']} covariates {[c['covariate'] for c in loc['covariates']]} "
      f"unpaired {len(loc['unpaired_clusters'])}; refits [{cands}]")
PY
done
