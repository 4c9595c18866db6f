//! One module per `equact` subcommand.

pub mod bench_ur;
pub mod config;
pub mod sim;
