//! One module per `equact` subcommand.

pub mod config;
pub mod inspect;
pub mod policy;
pub mod run;
