//! The campaign MCAP file: one per campaign, chunked and zstd-compressed, JSON messages with
//! JSON-schema encoding. The message types below are the single source of truth for the
//! channel schemas: their JSON Schemas are derived (schemars), embedded in the file, and
//! checked in under `schemas/mcap/` (a test fails on drift).
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

/// `/frf` and `/coherence`: one function record on an evenly spaced frequency axis
/// `f_k = freq_start_hz + k · freq_step_hz`, ordinates in SI (`ordinate_unit`).
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct FunctionMsg {
    pub measurement_id: String,
    pub node: i64,
    pub function_type: i32,
    pub response_direction: i32,
    pub reference_node: i64,
    pub reference_direction: i32,
    pub ordinate_unit: String,
    pub freq_start_hz: f64,
    pub freq_step_hz: f64,
    pub re: Vec<f64>,
    /// Empty for real functions (coherence).
    pub im: Vec<f64>,
}

/// `/balance`: one balance log line.
#[derive(Debug, Clone, Serialize, JsonSchema)]
pub struct BalanceMsg {
    pub file: String,
    pub line: u64,
    pub timestamp: Option<String>,
    pub board_id: Option<String>,
    pub response: String,
    pub status: String,
    pub value: Option<f64>,
    pub unit: Option<String>,
    pub mass_g: Option<f64>,
}

/// Channel topics, schema names and the JSON Schema of each channel's messages.
pub fn channel_schemas() -> Vec<(&'static str, &'static str, serde_json::Value)> {
    fn s<T: JsonSchema>() -> serde_json::Value {
        serde_json::to_value(schemars::schema_for!(T)).expect("schema serialises")
    }
    vec![
        ("/sheet", "hbmu.SheetRow", s::<SheetMsg>()),
        ("/scan_points", "hbmu.ScanPoints", s::<ScanPointsMsg>()),
        ("/frf", "hbmu.FunctionRecord", s::<FunctionMsg>()),
        ("/coherence", "hbmu.FunctionRecord", s::<FunctionMsg>()),
        ("/balance", "hbmu.BalanceReading", s::<BalanceMsg>()),
        (
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
        for (topic, name, schema) in channel_schemas() {
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
                .add_channel(sid, topic, "json", &BTreeMap::new())
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
        let data = serde_json::to_vec(msg).map_err(io::Error::other)?;
        self.write_encoded(topic, log_time_ns, &data)
    }

    /// Write one message already serialised as JSON (lets callers encode in parallel and
    /// write in a fixed order).
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
