//! Episode recordings in MCAP with Foxglove's well-known JSON schemas.
//!
//! One file per episode. Messages are JSON (`message_encoding = "json"`), each channel's
//! schema is a JSON Schema named after the Foxglove type it follows (`foxglove.JointStates`,
//! `foxglove.FrameTransforms`, `foxglove.RawImage`, `foxglove.PointCloud`,
//! `foxglove.SceneUpdate`, `foxglove.Log`), or `equact.*` for our own records (gripper state,
//! step events, episode outcome). The recording is written incrementally: chunks are closed
//! and flushed at every step ([`EpisodeRecorder::checkpoint`]), so a file cut short by a
//! crash or a power loss stays readable up to its last complete chunk. Dropping the recorder
//! finishes the file (summary, footer), so a fault unwinding through the episode loop still
//! leaves a complete file.

mod inspect;
mod messages;
mod schemas;

pub use inspect::{inspect_bytes, inspect_file, PhaseTiming, RecordingSummary};
pub use messages::{
    cloud_message, depth_image_message, frame_transform, joint_states_message,
    joint_trajectory_message, keyframe_scene, log_message, trajectory_scene, LogLevel,
};

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use serde::Serialize;
use thiserror::Error;

/// Every topic an episode recording may hold, with its schema name.
pub const TOPICS: &[(&str, &str)] = &[
    ("/robot_description", "equact.RobotDescription"),
    ("/joint_states", "foxglove.JointStates"),
    ("/tf", "foxglove.FrameTransforms"),
    ("/camera/depth", "foxglove.RawImage"),
    ("/cloud/fused", "foxglove.PointCloud"),
    ("/keyframes", "foxglove.SceneUpdate"),
    ("/trajectory/planned", "foxglove.SceneUpdate"),
    ("/trajectory/joints", "equact.JointTrajectory"),
    ("/gripper", "equact.GripperState"),
    ("/episode/step", "equact.StepEvent"),
    ("/episode/outcome", "equact.EpisodeOutcome"),
    ("/log", "foxglove.Log"),
];

/// Why a recording could not be written.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum RecordingError {
    /// The file could not be created or written.
    #[error("recording {path}: {source}; check that the recording folder exists and is writable (cell.toml: recording.dir)")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The MCAP writer refused a record.
    #[error("recording {path}: MCAP writer error: {message}")]
    Mcap {
        /// The file.
        path: PathBuf,
        /// The writer's message.
        message: String,
    },
    /// A recording could not be read.
    #[error("cannot read recording {path}: {source}; check the path")]
    Read {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A message was written to a topic that is not in [`TOPICS`].
    #[error("recording: unknown topic {topic}; add it to recording::TOPICS with its schema")]
    UnknownTopic {
        /// The topic.
        topic: String,
    },
    /// A message could not be encoded as JSON.
    #[error("recording: cannot encode a message for {topic}: {message}")]
    Encode {
        /// The topic.
        topic: String,
        /// The encoder's message.
        message: String,
    },
    /// The recording was already finished.
    #[error("recording {path} is already finished; start a new recorder for a new episode")]
    Finished {
        /// The file.
        path: PathBuf,
    },
}

/// Writes one episode's MCAP file.
pub struct EpisodeRecorder {
    path: PathBuf,
    writer: Option<mcap::Writer<BufWriter<File>>>,
    channels: BTreeMap<&'static str, u16>,
    sequence: u32,
    counts: BTreeMap<&'static str, u64>,
}

impl std::fmt::Debug for EpisodeRecorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EpisodeRecorder")
            .field("path", &self.path)
            .field("finished", &self.writer.is_none())
            .field("counts", &self.counts)
            .finish()
    }
}

/// Chunks close at this size at the latest (and at every checkpoint): small enough that a
/// crash loses little, large enough for lz4 to compress depth images well.
const CHUNK_BYTES: u64 = 4 * 1024 * 1024;

impl EpisodeRecorder {
    /// Creates the file, registers every schema and channel, and writes the episode's
    /// metadata (config, seed, versions) as an MCAP metadata record named `episode`.
    pub fn create(
        path: &Path,
        metadata: &BTreeMap<String, String>,
    ) -> Result<Self, RecordingError> {
        if let Some(parent) = path.parent() {
            if !parent.as_os_str().is_empty() {
                std::fs::create_dir_all(parent).map_err(|source| RecordingError::Io {
                    path: path.to_path_buf(),
                    source,
                })?;
            }
        }
        let file = File::create(path).map_err(|source| RecordingError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let mcap_err = |e: mcap::McapError| RecordingError::Mcap {
            path: path.to_path_buf(),
            message: e.to_string(),
        };
        let mut writer = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Lz4))
            .chunk_size(Some(CHUNK_BYTES))
            .profile("")
            .library(concat!("equact ", env!("CARGO_PKG_VERSION")))
            .create(BufWriter::new(file))
            .map_err(mcap_err)?;
        let mut schema_ids: BTreeMap<&str, u16> = BTreeMap::new();
        let mut channels = BTreeMap::new();
        for (topic, schema_name) in TOPICS {
            let schema_id = match schema_ids.get(schema_name) {
                Some(id) => *id,
                None => {
                    let text = schemas::schema_for(schema_name);
                    let id = writer
                        .add_schema(schema_name, "jsonschema", text.as_bytes())
                        .map_err(mcap_err)?;
                    schema_ids.insert(schema_name, id);
                    id
                }
            };
            let id = writer
                .add_channel(schema_id, topic, "json", &BTreeMap::new())
                .map_err(mcap_err)?;
            channels.insert(*topic, id);
        }
        writer
            .write_metadata(&mcap::records::Metadata {
                name: "episode".into(),
                metadata: metadata.clone(),
            })
            .map_err(mcap_err)?;
        Ok(Self {
            path: path.to_path_buf(),
            writer: Some(writer),
            channels,
            sequence: 0,
            counts: BTreeMap::new(),
        })
    }

    /// The file being written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Messages written so far, per topic.
    pub fn counts(&self) -> &BTreeMap<&'static str, u64> {
        &self.counts
    }

    /// Writes one message (serialised to JSON) on `topic` at `log_time_ns`.
    pub fn write<T: Serialize>(
        &mut self,
        topic: &str,
        log_time_ns: u64,
        message: &T,
    ) -> Result<(), RecordingError> {
        let data = serde_json::to_vec(message).map_err(|e| RecordingError::Encode {
            topic: topic.to_string(),
            message: e.to_string(),
        })?;
        self.write_raw(topic, log_time_ns, &data)
    }

    /// Writes one already-encoded JSON message on `topic`.
    pub fn write_raw(
        &mut self,
        topic: &str,
        log_time_ns: u64,
        data: &[u8],
    ) -> Result<(), RecordingError> {
        let (name, channel_id) = self
            .channels
            .get_key_value(topic)
            .map(|(k, v)| (*k, *v))
            .ok_or_else(|| RecordingError::UnknownTopic {
                topic: topic.to_string(),
            })?;
        let path = self.path.clone();
        let writer = self
            .writer
            .as_mut()
            .ok_or(RecordingError::Finished { path: path.clone() })?;
        self.sequence = self.sequence.wrapping_add(1);
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id,
                    sequence: self.sequence,
                    log_time: log_time_ns,
                    publish_time: log_time_ns,
                },
                data,
            )
            .map_err(|e| RecordingError::Mcap {
                path,
                message: e.to_string(),
            })?;
        *self.counts.entry(name).or_insert(0) += 1;
        Ok(())
    }

    /// Adds a file to the recording as an MCAP attachment (the URDF, the config file).
    pub fn attach(
        &mut self,
        name: &str,
        media_type: &str,
        log_time_ns: u64,
        data: &[u8],
    ) -> Result<(), RecordingError> {
        let path = self.path.clone();
        let writer = self
            .writer
            .as_mut()
            .ok_or(RecordingError::Finished { path: path.clone() })?;
        writer
            .attach(&mcap::Attachment {
                log_time: log_time_ns,
                create_time: log_time_ns,
                name: name.to_string(),
                media_type: media_type.to_string(),
                data: std::borrow::Cow::Borrowed(data),
            })
            .map_err(|e| RecordingError::Mcap {
                path,
                message: e.to_string(),
            })
    }

    /// Closes the current chunk and flushes it to disk, so everything written so far
    /// survives a crash. Call once per episode step.
    pub fn checkpoint(&mut self) -> Result<(), RecordingError> {
        let path = self.path.clone();
        let writer = self
            .writer
            .as_mut()
            .ok_or(RecordingError::Finished { path: path.clone() })?;
        writer.flush().map_err(|e| RecordingError::Mcap {
            path,
            message: e.to_string(),
        })
    }

    /// Writes the summary and footer. Also done on drop, but calling it reports errors.
    pub fn finish(&mut self) -> Result<(), RecordingError> {
        let Some(mut writer) = self.writer.take() else {
            return Ok(());
        };
        writer.finish().map_err(|e| RecordingError::Mcap {
            path: self.path.clone(),
            message: e.to_string(),
        })?;
        Ok(())
    }
}

impl Drop for EpisodeRecorder {
    fn drop(&mut self) {
        // A fault or panic unwinding through the episode loop still leaves a complete file.
        let _ = self.finish();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use cell_types::{FrameId, JointState, PointCloud};
    use nalgebra::Point3;

    fn write_sample(path: &Path, steps: usize) -> BTreeMap<&'static str, u64> {
        let mut meta = BTreeMap::new();
        meta.insert("seed".to_string(), "7".to_string());
        let mut rec = EpisodeRecorder::create(path, &meta).unwrap();
        for step in 0..steps {
            let t = step as u64 * 1_000_000_000;
            for k in 0..50u64 {
                let s = JointState::at_rest([0.1 * k as f64; 6]);
                rec.write(
                    "/joint_states",
                    t + k * 8_000_000,
                    &joint_states_message(t, &s),
                )
                .unwrap();
            }
            let cloud = PointCloud::new(
                FrameId::Base,
                (0..500)
                    .map(|i| Point3::new(i as f32 * 0.001, 0.0, 0.0))
                    .collect(),
                Some(vec![[10, 20, 30]; 500]),
            )
            .unwrap();
            rec.write("/cloud/fused", t, &cloud_message(t, &cloud))
                .unwrap();
            rec.write(
                "/episode/step",
                t,
                &serde_json::json!({"step": step, "phase": "plan", "duration_s": 0.002, "detail": ""}),
            )
            .unwrap();
            rec.checkpoint().unwrap();
        }
        rec.write(
            "/episode/outcome",
            steps as u64 * 1_000_000_000,
            &serde_json::json!({"outcome": "success", "success": true, "steps": steps, "detail": ""}),
        )
        .unwrap();
        let counts = rec.counts().clone();
        rec.finish().unwrap();
        counts
    }

    #[test]
    fn recording_reads_back_with_counts_and_outcome() {
        let dir = std::env::temp_dir().join(format!("equact-rec-{}", std::process::id()));
        let path = dir.join("a.mcap");
        let counts = write_sample(&path, 3);
        let s = inspect_file(&path).unwrap();
        assert!(s.complete);
        assert!(s.read_error.is_none());
        assert_eq!(
            s.topics["/joint_states"],
            ("foxglove.JointStates".to_string(), 150)
        );
        assert_eq!(s.topics["/cloud/fused"].1, counts["/cloud/fused"]);
        assert_eq!(s.outcome.as_ref().unwrap()["outcome"], "success");
        assert_eq!(s.phases["plan"].count, 3);
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn truncated_recording_keeps_complete_chunks() {
        let dir = std::env::temp_dir().join(format!("equact-trunc-{}", std::process::id()));
        let path = dir.join("b.mcap");
        write_sample(&path, 4);
        let bytes = std::fs::read(&path).unwrap();
        let full = inspect_bytes(&bytes);
        // Cut at every 997th byte: the reader never panics, never reports more messages
        // than the full file, and a cut past the first checkpoint keeps the first step.
        let mut kept_any = false;
        for cut in (8..bytes.len()).step_by(997) {
            let s = inspect_bytes(&bytes[..cut]);
            assert!(s.message_count() <= full.message_count());
            assert!(!s.complete);
            if s.topics.get("/joint_states").map_or(0, |t| t.1) >= 50 {
                kept_any = true;
            }
        }
        assert!(kept_any);
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn unknown_topic_and_writes_after_finish_are_errors() {
        let dir = std::env::temp_dir().join(format!("equact-unk-{}", std::process::id()));
        let path = dir.join("c.mcap");
        let mut rec = EpisodeRecorder::create(&path, &BTreeMap::new()).unwrap();
        assert!(matches!(
            rec.write("/nope", 0, &serde_json::json!({})),
            Err(RecordingError::UnknownTopic { .. })
        ));
        rec.finish().unwrap();
        assert!(matches!(
            rec.write("/log", 0, &log_message(0, LogLevel::Info, "x")),
            Err(RecordingError::Finished { .. })
        ));
        std::fs::remove_dir_all(dir).ok();
    }

    #[test]
    fn dropping_the_recorder_finishes_the_file() {
        let dir = std::env::temp_dir().join(format!("equact-drop-{}", std::process::id()));
        let path = dir.join("d.mcap");
        {
            let mut rec = EpisodeRecorder::create(&path, &BTreeMap::new()).unwrap();
            rec.write("/log", 5, &log_message(5, LogLevel::Error, "fault"))
                .unwrap();
        }
        let s = inspect_file(&path).unwrap();
        assert!(s.complete);
        assert_eq!(s.topics["/log"].1, 1);
        std::fs::remove_dir_all(dir).ok();
    }
}
