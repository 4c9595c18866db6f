//! The `equact` application library: the episode loop, MCAP recording and the pieces of the
//! CLI that tests exercise directly. The binary (`src/main.rs`) only parses arguments and
//! sets the allocator to keep freed memory (`libc::mallopt`, glibc only; see its doc).
//!
//! Libraries: `mcap` (the reference Rust MCAP writer/reader; lz4 chunk compression only, so
//! a single small C library is built), `serde_json` + `base64` for Foxglove's JSON message
//! encoding, `ctrlc` to turn Ctrl-C into a controlled stop.

pub mod calibrate_capture;
pub mod demos;
pub mod episode;
pub mod eval;
pub mod eval_compare;
pub mod eval_report;
pub mod follow;
pub mod grounding;
pub mod learned;
pub mod plot;
pub mod preflight;
pub mod real_cell;
pub mod recording;
pub mod score;
pub mod sim_cell;
pub mod stats;
pub mod task;
pub mod train;
