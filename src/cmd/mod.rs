//! One module per `equact` subcommand, and `args` for helpers they share.

pub mod args;
pub mod bench;
pub mod bench_attention;
pub mod bench_matmul;
pub mod bench_ur;
pub mod calibrate;
pub mod check;
pub mod config;
pub mod demos;
pub mod eval;
pub mod gripper;
pub mod inspect;
pub mod perceive;
pub mod plan;
pub mod plot;
pub mod policy;
pub mod run;
pub mod sim;
pub mod train;
