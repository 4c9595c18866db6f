//! One module per `equact` subcommand.

pub mod config;
pub mod perceive;
