//! `equact`: the command-line front end of the cell stack.

fn main() {}
