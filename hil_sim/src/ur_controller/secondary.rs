//! The secondary interface (TCP 30002) as a script sink: a URScript program arrives as text
//! (`def name(): ... end`). Our servo program is recognised by its contract header
//! (`firmware_iface::urscript`) and run by [`super::core`]; any other program is reported as
//! a text message and not run (the simulator does not interpret URScript).

use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::sync::Arc;

use firmware_iface::urscript::ServoParams;

use super::Shared;

/// Largest program accepted (bytes).
pub const MAX_PROGRAM: usize = 1 << 20;

/// Serves one secondary-interface connection.
pub(crate) fn serve(shared: Arc<Shared>, stream: TcpStream, id: u64) {
    let reason = run(&shared, &stream);
    shared.log(format!("secondary connection {id} closed: {reason}"));
    let _ = stream.shutdown(std::net::Shutdown::Both);
}

fn run(shared: &Shared, stream: &TcpStream) -> String {
    let mut reader = BufReader::new(stream);
    let mut program = String::new();
    let mut line = String::new();
    loop {
        line.clear();
        match reader.read_line(&mut line) {
            Ok(0) if program.trim().is_empty() => return "client disconnected".into(),
            Ok(0) => return "client disconnected before the program's closing `end`".into(),
            Ok(_) => {}
            Err(e) => return format!("read failed: {e}"),
        }
        if shared.stopping() {
            return "simulator shutting down".into();
        }
        program.push_str(&line);
        if program.len() > MAX_PROGRAM {
            return format!("program longer than {MAX_PROGRAM} bytes");
        }
        // A top-level program ends with an unindented `end`.
        if line.trim_end() == "end" && program.trim_start().starts_with("def ") {
            run_program(shared, &program);
            program.clear();
        } else if !program.trim_start().starts_with("def ") && !program.trim().is_empty() {
            shared.broadcast_text(
                format!("secondary: ignored line outside a program: {}", line.trim()),
                2,
            );
            program.clear();
        }
    }
}

fn run_program(shared: &Shared, program: &str) {
    match ServoParams::recognise(program) {
        Ok(params) => {
            let started = shared.core().start_servo_program(params);
            if let Err(why) = started {
                shared.broadcast_text(why, 1);
            }
        }
        Err(e) => shared.broadcast_text(format!("unknown program not run: {e}"), 1),
    }
}
