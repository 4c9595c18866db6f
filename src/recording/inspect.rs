//! Reading a recording back: topics, message counts, the outcome and the step timings.
//! Reads files cut short by a crash too, up to their last complete chunk.

use std::collections::BTreeMap;
use std::path::Path;

use serde::Serialize;
use serde_json::Value;

use super::RecordingError;

/// Per-phase timing statistics from the `/episode/step` events.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct PhaseTiming {
    /// Number of events.
    pub count: u64,
    /// Sum of durations (s).
    pub total_s: f64,
    /// Longest duration (s).
    pub max_s: f64,
}

/// What a recording holds.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RecordingSummary {
    /// Messages per topic, with the topic's schema name.
    pub topics: BTreeMap<String, (String, u64)>,
    /// The `/episode/outcome` message, if the episode got that far.
    pub outcome: Option<Value>,
    /// Step timings per phase (capture, fuse, predict, plan, execute, gripper).
    pub phases: BTreeMap<String, PhaseTiming>,
    /// True when the file ends properly (summary and footer written).
    pub complete: bool,
    /// Why reading stopped early, for a truncated or damaged file.
    pub read_error: Option<String>,
    /// Log time of the first and last message (ns).
    pub time_range_ns: Option<(u64, u64)>,
}

impl RecordingSummary {
    /// Total messages read.
    pub fn message_count(&self) -> u64 {
        self.topics.values().map(|(_, n)| n).sum()
    }
}

/// Reads a recording file and summarises it.
pub fn inspect_file(path: &Path) -> Result<RecordingSummary, RecordingError> {
    let bytes = std::fs::read(path).map_err(|source| RecordingError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    Ok(inspect_bytes(&bytes))
}

/// Summarises recording bytes; a truncated file yields what its complete chunks hold.
pub fn inspect_bytes(bytes: &[u8]) -> RecordingSummary {
    let mut summary = RecordingSummary {
        complete: mcap::read::footer(bytes).is_ok(),
        ..Default::default()
    };
    let options = enumset::enum_set!(mcap::read::Options::IgnoreEndMagic);
    let stream = match mcap::MessageStream::new_with_options(bytes, options) {
        Ok(s) => s,
        Err(e) => {
            summary.read_error = Some(e.to_string());
            return summary;
        }
    };
    for message in stream {
        let message = match message {
            Ok(m) => m,
            Err(e) => {
                summary.read_error = Some(e.to_string());
                break;
            }
        };
        let topic = message.channel.topic.clone();
        let schema = message
            .channel
            .schema
            .as_ref()
            .map(|s| s.name.clone())
            .unwrap_or_default();
        summary.topics.entry(topic.clone()).or_insert((schema, 0)).1 += 1;
        let t = message.log_time;
        summary.time_range_ns = Some(match summary.time_range_ns {
            None => (t, t),
            Some((a, b)) => (a.min(t), b.max(t)),
        });
        if topic == "/episode/outcome" || topic == "/episode/step" {
            let Ok(value) = serde_json::from_slice::<Value>(&message.data) else {
                continue;
            };
            if topic == "/episode/outcome" {
                summary.outcome = Some(value);
            } else {
                let phase = value["phase"].as_str().unwrap_or("?").to_string();
                let d = value["duration_s"].as_f64().unwrap_or(0.0);
                let entry = summary.phases.entry(phase).or_default();
                entry.count += 1;
                entry.total_s += d;
                entry.max_s = entry.max_s.max(d);
            }
        }
    }
    summary
}
