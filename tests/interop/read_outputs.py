#!/usr/bin/env python3
"""Read hbmu ingest outputs with third-party clients and check them against schemas/.

Usage: read_outputs.py INGEST_DIR SCHEMAS_DIR
- every Parquet table through pandas (pyarrow engine): documented columns present, dtypes as
  documented, units/provenance metadata in both the Arrow schema and the Parquet footer;
- campaign.mcap through the official `mcap` Python reader: every channel, its schema (JSON
  schema encoding, equal to the file in schemas/mcap/), every message decodes in its channel's
  encoding: JSON, or CBOR (cbor2) for the spectra, whose ordinates are little-endian float64
  byte strings.
Prints a JSON summary on stdout; exits non-zero on the first violation.
"""
import json
import os
import sys

import pandas as pd
import pyarrow.parquet as pq
from mcap.reader import make_reader
import cbor2
import numpy as np

out, schemas = sys.argv[1], sys.argv[2]
summary = {"tables": {}, "mcap": {}}

KIND = {
    "string": lambda s: pd.api.types.is_string_dtype(s) or s.dtype == object,
    "int32": lambda s: str(s.dtype) in ("int32", "Int32"),
    "int64": lambda s: str(s.dtype) in ("int64", "Int64"),
    "float64": lambda s: str(s.dtype) == "float64",
    "bool": lambda s: str(s.dtype) in ("bool", "boolean"),
    "list<float64>": lambda s: s.dtype == object,
    "list<int64>": lambda s: s.dtype == object,
}

for fn in sorted(os.listdir(os.path.join(schemas, "tables"))):
    name = fn[:-5]
    path = os.path.join(out, name + ".parquet")
    if not os.path.exists(path):
        continue
    spec = json.load(open(os.path.join(schemas, "tables", fn)))
    df = pd.read_parquet(path, engine="pyarrow")
    for col, p in spec["properties"].items():
        assert col in df.columns, f"{name}: column {col} missing"
        kind = p["x-arrow-type"]
        nullable = "anyOf" in p
        s = df[col]
        if nullable and kind in ("int32", "int64", "bool") and s.isna().any():
            assert s.dtype in (float, object) or str(s.dtype)[0] in "fIBO", (name, col, s.dtype)
        else:
            assert KIND[kind](s), f"{name}.{col}: expected {kind}, pandas dtype {s.dtype}"
        if kind.startswith("list") and len(s.dropna()):
                        assert isinstance(s.dropna().iloc[0], np.ndarray), f"{name}.{col}: cells should be numpy arrays"
    if not spec.get("additionalProperties", False):
        extra = set(df.columns) - set(spec["properties"])
        assert not extra, f"{name}: undocumented columns {extra}"
    footer = pq.read_metadata(path).metadata
    schema_md = pq.read_schema(path).metadata
    for md, where in ((footer, "footer"), (schema_md, "arrow schema")):
        for k in (b"hbmu.units", b"hbmu.fingerprint", b"hbmu.campaign", b"hbmu.table"):
            assert k in md, f"{name}: {k!r} missing from {where} metadata"
        assert b"pandas" not in md, f"{name}: unexpected pandas metadata in {where}"
    units = json.loads(footer[b"hbmu.units"])
    for col, p in spec["properties"].items():
        if "x-unit" in p:
            assert units.get(col) == p["x-unit"], (name, col, units.get(col), p["x-unit"])
    summary["tables"][name] = {"rows": len(df), "columns": list(df.columns)}

with open(os.path.join(out, "campaign.mcap"), "rb") as f:
    reader = make_reader(f)
    s = reader.get_summary()
    assert s is not None, "no summary section"
    assert all(ch.compression in ("zstd", "lz4") for ch in s.chunk_indexes), "chunks must be compressed"
    assert len(s.chunk_indexes) >= 1
    for cid, ch in s.channels.items():
        sch = s.schemas[ch.schema_id]
        assert sch.encoding == "jsonschema", sch.encoding
        want = "cbor" if ch.topic in ("/frf", "/coherence") else "json"
        assert ch.message_encoding == want, (ch.topic, ch.message_encoding)
        on_disk = json.load(open(os.path.join(schemas, "mcap", sch.name.split(".", 1)[1] + ".json")))
        on_disk.pop("x-mcap-schema-name", None)
        assert json.loads(sch.data) == on_disk, f"embedded schema {sch.name} differs from schemas/"
        summary["mcap"][ch.topic] = {"schema": sch.name, "messages": s.statistics.channel_message_counts.get(cid, 0)}
    n = 0
    frf_msgs = {}
    for sch, ch, msg in reader.iter_messages():
        if ch.message_encoding == "cbor":
            m = cbor2.loads(msg.data)
            for k in ("re", "im"):
                assert isinstance(m[k], bytes) and len(m[k]) % 8 == 0, (ch.topic, k)
                m[k] = np.frombuffer(m[k], "<f8")
        else:
            m = json.loads(msg.data)
        if ch.topic == "/frf":
            frf_msgs[(m["measurement_id"], m["node"])] = m
        n += 1
    summary["mcap_messages"] = n
    meta = [m for m in reader.iter_metadata()]
    summary["mcap_metadata"] = [m.name for m in meta]
# frf.parquet: the README's recipe rebuilds the axis, and it agrees with the MCAP's spectra.
frf = pd.read_parquet(os.path.join(out, "frf.parquet"))
frf["freq_hz"] = [r.freq_start_hz + r.freq_step_hz * np.arange(r.n_lines) for r in frf.itertuples()]
resp = frf[frf.function_type != 6]
long = resp.explode(["freq_hz", "re", "im"])
assert len(long) == int(resp["n_lines"].sum()), "explode gives one row per spectral line"
checked = 0
for r in frf[frf.function_type != 6].itertuples():
    assert len(r.re) == r.n_lines, (r.measurement_id, r.node)
    m = frf_msgs[(r.measurement_id, r.node)]
    assert m["freq_start_hz"] == r.freq_start_hz and m["freq_step_hz"] == r.freq_step_hz
    assert np.array_equal(np.asarray(m["re"]), r.re) and np.array_equal(np.asarray(m["im"]), r.im)
    checked += 1
assert checked == len(frf_msgs), (checked, len(frf_msgs))
summary["frf_records_checked_against_mcap"] = checked
print(json.dumps(summary))
