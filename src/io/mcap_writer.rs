//! The campaign MCAP file: one per campaign, chunked and zstd-compressed, every channel with a
//! JSON-schema. The message types below are the single source of truth for the channel
//! schemas: their JSON Schemas are derived (schemars), embedded in the file, and checked in
//! under `schemas/mcap/` (a test fails on drift).
//!
//! Message encodings: JSON (`json`) for the small, human-readable channels; CBOR (`cbor`,
//! RFC 8949, a well-known MCAP message encoding) for the spectra, `/frf` and `/coherence`,
//! whose ordinates are CBOR byte strings of little-endian IEEE 754 binary64 values. Spectra are
//! nearly all of the file: as JSON text they took 2.5× their binary size before compression
//! and most of the stage's time in float formatting and compressing text.
//!
//! Channels: `/sheet` (one message per measurement row), `/scan_points` (geometry of one
//! measurement), `/frf` (one response record), `/coherence` (one coherence record), `/balance`
//! (one balance line), `/ingest/findings` (one finding). Log time is the measurement's date
//! where known (balance: the reading's timestamp), else 0; messages are written in a fixed
//! order so the file is byte-identical across runs.

use schemars::JsonSchema;
use serde::Serialize;
use std::collections::BTreeMap;
use std::io::{self, Seek, Write};

/// `/sheet`: one measurement row and its ingest status.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct SheetMsg {
    pub measurement_id: String,
    pub board_id: String,
    pub setup: String,
    pub file: String,
    pub bolt_set: Option<String>,
    pub torque_nm: Option<f64>,
    pub temperature_c: Option<f64>,
    pub date: Option<String>,
    pub operator: Option<String>,
    pub notes: Option<String>,
    /// Extra sheet columns, verbatim.
    pub extra: BTreeMap<String, String>,
    pub sheet_line: u64,
    /// `ok` or `quarantined`.
    pub status: String,
    pub status_reason: Option<String>,
}

/// One scan point, metres, board frame.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct PointMsg {
    pub node: i64,
    pub x_m: f64,
    pub y_m: f64,
    pub z_m: f64,
    pub is_reference: bool,
}

/// `/scan_points`: the geometry of one measurement.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct ScanPointsMsg {
    pub measurement_id: String,
    pub points: Vec<PointMsg>,
}

/// `/vendor_modes`: one mode a lab's modal software identified (UFF dataset 55); see
/// vendor_modes.parquet.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct VendorModeMsg<'a> {
    pub measurement_id: &'a str,
    pub mode: i32,
    pub mode_number: Option<i64>,
    pub analysis_type: i64,
    pub uff_line: u64,
    pub freq_hz: f64,
    pub damping_ratio: f64,
    pub mpc: f64,
    pub mpd_deg: f64,
    pub node: &'a [i64],
    pub shape: &'a [f64],
}

/// `/frf` and `/coherence` (CBOR): one function record on an evenly spaced frequency axis
/// `f_k = freq_start_hz + k · freq_step_hz`, ordinates in SI (`ordinate_unit`).
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct FunctionMsg<'a> {
    pub measurement_id: &'a str,
    pub node: i64,
    pub function_type: i32,
    pub response_direction: i32,
    pub reference_node: i64,
    pub reference_direction: i32,
    pub ordinate_unit: &'a str,
    /// What the lab measured, numerator/denominator (`acceleration/force`, ...; see
    /// frf.parquet): the ordinates are converted to `ordinate_unit`.
    pub measured_as: &'a str,
    pub freq_start_hz: f64,
    pub freq_step_hz: f64,
    /// Real parts, one per spectral line: a CBOR byte string of little-endian IEEE 754
    /// binary64 values, 8 bytes each (numpy: `np.frombuffer(b, "<f8")`).
    #[schemars(schema_with = "f64_le_schema")]
    pub re: F64Le<'a>,
    /// Imaginary parts, encoded as `re`; empty for real functions (coherence).
    #[schemars(schema_with = "f64_le_schema")]
    pub im: F64Le<'a>,
}

/// A float64 array serialised as one byte string of little-endian IEEE 754 binary64 values
/// (8 bytes per value): in CBOR a single length-prefixed byte string, so a spectrum is written
/// without per-value formatting and read back with one `np.frombuffer(b, "<f8")`.
#[derive(Debug, Clone, Copy)]
pub struct F64Le<'a>(pub &'a [f64]);

impl Serialize for F64Le<'_> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        if cfg!(target_endian = "little") {
            s.serialize_bytes(bytemuck::cast_slice(self.0))
        } else {
            let bytes: Vec<u8> = self.0.iter().flat_map(|v| v.to_le_bytes()).collect();
            s.serialize_bytes(&bytes)
        }
    }
}

fn f64_le_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
    schemars::json_schema!({
        "description": "CBOR byte string: little-endian IEEE 754 binary64 values, 8 bytes each (numpy: np.frombuffer(b, \"<f8\")).",
        "x-cbor-type": "bytes",
        "x-dtype": "<f8"
    })
}

/// An MCAP message encoding of ours.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Encoding {
    Json,
    Cbor,
}

impl Encoding {
    /// The MCAP `message_encoding` string.
    pub fn as_str(self) -> &'static str {
        match self {
            Encoding::Json => "json",
            Encoding::Cbor => "cbor",
        }
    }

    /// Serialise one message.
    pub fn encode<T: Serialize + ?Sized>(self, msg: &T) -> io::Result<Vec<u8>> {
        let mut buf = Vec::new();
        self.encode_into(msg, &mut buf)?;
        Ok(buf)
    }

    /// Serialise one message, appending to `buf` (lets a caller reuse one buffer).
    pub fn encode_into<T: Serialize + ?Sized>(self, msg: &T, buf: &mut Vec<u8>) -> io::Result<()> {
        match self {
            Encoding::Json => serde_json::to_writer(&mut *buf, msg).map_err(io::Error::other),
            Encoding::Cbor => ciborium::into_writer(msg, &mut *buf).map_err(io::Error::other),
        }
    }
}

/// The message encoding of a topic: CBOR for the spectra, JSON for everything else.
pub fn encoding_of(topic: &str) -> Encoding {
    match topic {
        "/frf" | "/coherence" => Encoding::Cbor,
        _ => Encoding::Json,
    }
}

/// `/balance`: one balance log line.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct BalanceMsg {
    pub file: String,
    pub line: u64,
    pub timestamp: Option<String>,
    /// The ID as written in the log.
    pub board_id: Option<String>,
    /// The sheet's board the line counts for (null: not a board of the sheet).
    pub sheet_board_id: Option<String>,
    pub response: String,
    pub status: String,
    pub value: Option<f64>,
    pub unit: Option<String>,
    pub mass_g: Option<f64>,
}

/// One channel of the campaign file.
pub struct ChannelSpec {
    pub topic: &'static str,
    pub schema_name: &'static str,
    pub message_encoding: Encoding,
    /// JSON Schema of the (decoded) messages.
    pub schema: serde_json::Value,
}

/// Every channel: topic, schema name, message encoding and the JSON Schema of its messages.
pub fn channel_schemas() -> Vec<ChannelSpec> {
    fn s<T: JsonSchema>() -> serde_json::Value {
        serde_json::to_value(schemars::schema_for!(T)).expect("schema serialises")
    }
    let c = |topic, schema_name, schema| ChannelSpec {
        topic,
        schema_name,
        message_encoding: encoding_of(topic),
        schema,
    };
    vec![
        c("/sheet", "hbmu.SheetRow", s::<SheetMsg>()),
        c("/scan_points", "hbmu.ScanPoints", s::<ScanPointsMsg>()),
        c("/frf", "hbmu.FunctionRecord", s::<FunctionMsg>()),
        c("/coherence", "hbmu.FunctionRecord", s::<FunctionMsg>()),
        c("/vendor_modes", "hbmu.VendorMode", s::<VendorModeMsg>()),
        c("/balance", "hbmu.BalanceReading", s::<BalanceMsg>()),
        c(
            "/ingest/findings",
            "hbmu.Finding",
            s::<crate::findings::Finding>(),
        ),
    ]
}

/// A thin wrapper over `mcap::Writer` that registers our channels and serialises messages.
pub struct CampaignMcap<W: Write + Seek> {
    writer: mcap::Writer<W>,
    channels: BTreeMap<&'static str, u16>,
    sequence: u32,
}

fn mcap_err(e: mcap::McapError) -> io::Error {
    io::Error::other(e)
}

impl<W: Write + Seek> CampaignMcap<W> {
    /// Start a file: header, schemas, channels, and a metadata record `campaign` with `meta`.
    pub fn create(w: W, meta: &BTreeMap<String, String>) -> io::Result<Self> {
        let opts = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(4 << 20))
            // Single-threaded zstd: identical bytes whatever the machine's core count.
            .compression_threads(0)
            // Level 1: the spectra are most of the bytes, and level 1 compresses them at several
            // hundred MB/s, where the default level made this file the stage's bottleneck.
            .compression_level(1)
            .profile("")
            .library(format!("hbmu {}", crate::io::manifest::TOOL_VERSION));
        let mut writer = opts.create(w).map_err(mcap_err)?;
        let mut channels = BTreeMap::new();
        let mut schema_ids: BTreeMap<&str, u16> = BTreeMap::new();
        for ChannelSpec {
            topic,
            schema_name: name,
            message_encoding,
            schema,
        } in channel_schemas()
        {
            let sid = match schema_ids.get(name) {
                Some(id) => *id,
                None => {
                    let bytes = serde_json::to_vec(&schema).map_err(io::Error::other)?;
                    let id = writer
                        .add_schema(name, "jsonschema", &bytes)
                        .map_err(mcap_err)?;
                    schema_ids.insert(name, id);
                    id
                }
            };
            let cid = writer
                .add_channel(sid, topic, message_encoding.as_str(), &BTreeMap::new())
                .map_err(mcap_err)?;
            channels.insert(topic, cid);
        }
        writer
            .write_metadata(&mcap::records::Metadata {
                name: "campaign".into(),
                metadata: meta.clone(),
            })
            .map_err(mcap_err)?;
        Ok(CampaignMcap {
            writer,
            channels,
            sequence: 0,
        })
    }

    /// Write one message on `topic` with `log_time_ns`.
    pub fn write<T: Serialize>(
        &mut self,
        topic: &str,
        log_time_ns: u64,
        msg: &T,
    ) -> io::Result<()> {
        let data = encoding_of(topic).encode(msg)?;
        self.write_encoded(topic, log_time_ns, &data)
    }

    /// Write one message already serialised in its topic's [`encoding_of`] (lets callers
    /// encode in parallel and write in a fixed order).
    pub fn write_encoded(&mut self, topic: &str, log_time_ns: u64, data: &[u8]) -> io::Result<()> {
        let channel_id = *self
            .channels
            .get(topic)
            .ok_or_else(|| io::Error::other(format!("unknown MCAP topic {topic}")))?;
        self.sequence += 1;
        self.writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: self.sequence,
                    log_time: log_time_ns,
                    publish_time: log_time_ns,
                },
                data,
            )
            .map_err(mcap_err)
    }

    /// Write the summary section and footer.
    pub fn finish(mut self) -> io::Result<()> {
        self.writer.finish().map_err(mcap_err)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A spectrum written on `/frf` comes back from the MCAP reader as a CBOR map whose `re`
    /// and `im` byte strings are the values, bit for bit, in little-endian float64; the small
    /// channels stay JSON.
    #[test]
    fn spectra_round_trip_as_cbor_float64_byte_strings() {
        let re = [1.0, -2.5e-7, f64::MIN_POSITIVE, 1.0 / 3.0];
        let im = [0.0, 1e300, -0.0, 7.25];
        let mut file = std::io::Cursor::new(Vec::new());
        let mut w = CampaignMcap::create(&mut file, &BTreeMap::new()).unwrap();
        w.write(
            "/frf",
            5,
            &FunctionMsg {
                measurement_id: "M001",
                node: 12,
                function_type: 4,
                response_direction: 3,
                reference_node: 1,
                reference_direction: 3,
                ordinate_unit: "(m/s)/N",
                measured_as: "velocity/force",
                freq_start_hz: 0.0,
                freq_step_hz: 2.5,
                re: F64Le(&re),
                im: F64Le(&im),
            },
        )
        .unwrap();
        w.write(
            "/scan_points",
            5,
            &ScanPointsMsg {
                measurement_id: "M001".into(),
                points: vec![],
            },
        )
        .unwrap();
        w.finish().unwrap();
        let bytes = file.into_inner();
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let mut seen = 0;
        for msg in mcap::MessageStream::new(&bytes).unwrap() {
            let msg = msg.unwrap();
            let ch = &summary.channels[&msg.channel.id];
            match ch.topic.as_str() {
                "/frf" => {
                    assert_eq!(ch.message_encoding, "cbor");
                    let v: ciborium::Value = ciborium::from_reader(&msg.data[..]).unwrap();
                    let map = v.as_map().unwrap();
                    let get = |k: &str| {
                        map.iter()
                            .find(|(key, _)| key.as_text() == Some(k))
                            .map(|(_, v)| v.clone())
                            .unwrap()
                    };
                    for (k, want) in [("re", &re), ("im", &im)] {
                        let b = get(k).into_bytes().unwrap();
                        let got: Vec<f64> = b
                            .chunks_exact(8)
                            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                            .collect();
                        assert_eq!(got.len(), want.len());
                        for (g, w) in got.iter().zip(want.iter()) {
                            assert_eq!(g.to_bits(), w.to_bits(), "{k}");
                        }
                    }
                    assert_eq!(get("node").as_integer().map(i128::from), Some(12));
                    assert_eq!(get("measurement_id").as_text(), Some("M001"));
                    seen += 1;
                }
                "/scan_points" => {
                    assert_eq!(ch.message_encoding, "json");
                    let v: serde_json::Value = serde_json::from_slice(&msg.data).unwrap();
                    assert_eq!(v["measurement_id"], "M001");
                    seen += 1;
                }
                t => panic!("unexpected topic {t}"),
            }
        }
        assert_eq!(seen, 2);
    }
}
