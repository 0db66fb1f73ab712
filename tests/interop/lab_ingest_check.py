"""Check that `hbmu ingest` reports exactly the deliberate imperfections of a virtual-lab
campaign, as listed in its truth file, and nothing else.

Usage: python3 lab_ingest_check.py TRUTH.json INGEST_REPORT.json
Exit status 0 when the findings match, 1 otherwise (the differences are printed).

Deliberate imperfections the lab writes (src/lab/measure.rs):
- scan points without a record   -> info `uff.points_without_record`, one per measurement
  with missing nodes, naming their number;
- garbled stable balance lines   -> record_dropped `balance.unknown_response` at file:line.
Mostly-noise records (speckle drop-outs) and busy/error/unsettled balance lines are
normal data, not findings.
"""
import collections
import json
import re
import sys


def main(truth_path, report_path):
    truth = json.load(open(truth_path))
    report = json.load(open(report_path))
    problems = []
    expect_missing = {m["measurement_id"]: len(m["missing_nodes"]) for m in truth["measurements"] if m["missing_nodes"]}
    expect_garbled = sorted(truth.get("garbled_balance_lines", []))
    got_missing, got_garbled, other = {}, [], []
    for f in report["findings"]:
        if f["code"] == "uff.points_without_record":
            n = int(re.match(r"(\d+) scan point", f["message"]).group(1))
            got_missing[f["measurement_id"]] = n
        elif f["code"] == "balance.unknown_response":
            got_garbled.append(f"{f['file']}:{f['line']}")
        else:
            other.append(f)
    if got_missing != expect_missing:
        problems.append(f"points without record: expected {expect_missing}, found {got_missing}")
    if sorted(got_garbled) != expect_garbled:
        problems.append(f"garbled balance lines: expected {expect_garbled}, found {sorted(got_garbled)}")
    if other:
        counts = collections.Counter(f["code"] for f in other)
        problems.append(f"unexpected findings: {dict(counts)}; first: {other[0]}")
    if report.get("quarantined"):
        problems.append(f"quarantined measurements: {report['quarantined']}")
    for p in problems:
        print(p)
    if not problems:
        print(f"ok: {len(expect_missing)} measurement(s) with missing points, "
              f"{len(expect_garbled)} garbled balance line(s), nothing else")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
