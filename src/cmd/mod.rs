//! One module per `equact` subcommand.

pub mod bench;
pub mod config;
pub mod plan;
