#!/usr/bin/env bash
# Benchmark of the hierarchical updating at the issue's size: step 1 with 2000 particles × 4
# runs and step 2 with 2000 particles × 4 runs on the demo campaign (the paper-like virtual
# campaign: 7 boards, 35 free-free and 30 bolted measurements). Prints wall and CPU seconds
# and the sampler's own diagnostics. Usage: benches/update.sh WORK_DIR HBMU [EXTRA ARGS...]
# (WORK_DIR = a demo work directory with ingest/, pair/, extract/).
set -euo pipefail
work=$1
hbmu=$2
shift 2
out=$(mktemp -d /tmp/hbmu-bench-update.XXXXXX)
trap 'rm -rf "$out"' EXIT
for step in boards joints; do
  extra=()
  if [ "$step" = joints ]; then extra=(--boards "$out/boards"); fi
  /usr/bin/env time -f "$step: %e s wall, %U s user, %S s system, %M kB max RSS" \
    "$hbmu" update "$step" "$work/ingest" "$work/pair" --extract "$work/extract" \
    --particles 2000 --runs 4 --out "$out/$step" --force "${extra[@]}" "$@" 2>&1 | grep -E "^update|wall"
  python3 - "$out/$step/update_report.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
a = d["acceleration"]
print(f"  stages per run {d['stages_per_run']}, max R-hat {d['max_r_hat']:.4f}, min ESS {d['min_ess']:.0f}, "
      f"log evidence runs {[round(x, 2) for x in d['evidence']['log_evidence_runs']]}, "
      f"correction ESS {[round(x) for x in a['correction_ess']]}")
PY
done
