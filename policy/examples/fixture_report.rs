//! Prints every comparison of one fixture file: `cargo run -p policy --example
//! fixture_report -- policy/tests/fixtures/so2_conv.safetensors`.

use std::path::PathBuf;

use policy::fixtures::{check_file, Outcome};

fn main() {
    let Some(path) = std::env::args().nth(1).map(PathBuf::from) else {
        eprintln!("usage: fixture_report FIXTURE.safetensors");
        std::process::exit(2);
    };
    let report = check_file(&path);
    println!("{}", report.line());
    if let Outcome::Checked(cs) = &report.outcome {
        for c in cs {
            println!(
                "  {} {:<40} max_abs {:.3e} rel {:.3e} scaled {:.3e} / tol {:.0e}",
                if c.passed() { "ok  " } else { "FAIL" },
                c.what,
                c.max_abs,
                c.rel,
                c.scaled,
                c.tolerance
            );
        }
    }
    if !report.passed() {
        std::process::exit(1);
    }
}
