//! The dashboard server (TCP 29999; UR fact sheet "Dashboard server"): newline-terminated
//! commands answered from the controller's robot/safety state machine in [`super::core`].

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::sync::Arc;

use firmware_iface::dashboard::{
    program_state_reply, robot_mode_reply, running_reply, safety_mode_reply, safety_status_reply,
    DashboardCommand, ProgramState, GREETING, UNLOCK_TOO_EARLY,
};

use super::Shared;

/// Longest line accepted; anything longer is not a dashboard command.
pub const MAX_LINE: usize = 1024;

/// Serves one dashboard connection.
pub(crate) fn serve(shared: Arc<Shared>, stream: TcpStream, id: u64) {
    let reason = run(&shared, &stream);
    shared.log(format!("dashboard connection {id} closed: {reason}"));
    let _ = stream.shutdown(std::net::Shutdown::Both);
}

fn run(shared: &Shared, stream: &TcpStream) -> String {
    let mut w = stream;
    if let Err(e) = writeln!(w, "{GREETING}") {
        return format!("write failed: {e}");
    }
    let mut reader = BufReader::new(stream);
    let mut line = Vec::with_capacity(128);
    loop {
        line.clear();
        match (&mut reader)
            .take(MAX_LINE as u64 + 1)
            .read_until(b'\n', &mut line)
        {
            Ok(0) => return "client disconnected".into(),
            Ok(_) => {}
            Err(e) => return format!("read failed: {e}"),
        }
        if line.len() > MAX_LINE {
            return format!("line longer than {MAX_LINE} bytes");
        }
        if shared.stopping() {
            return "simulator shutting down".into();
        }
        let Ok(text) = std::str::from_utf8(&line) else {
            return "line is not UTF-8 text".into();
        };
        if !text.ends_with('\n') {
            return "client disconnected in the middle of a line".into();
        }
        let (reply, quit) = answer(shared, text);
        if let Err(e) = writeln!(w, "{reply}") {
            return format!("write failed: {e}");
        }
        if quit {
            return "client sent quit".into();
        }
    }
}

/// The reply to one command line, and whether the connection ends.
fn answer(shared: &Shared, line: &str) -> (String, bool) {
    let Ok(cmd) = DashboardCommand::parse(line) else {
        return (format!("could not understand: '{}'", line.trim()), false);
    };
    let mut core = shared.core();
    let reply = match cmd {
        DashboardCommand::PowerOn => {
            core.power_on();
            "Powering on".to_string()
        }
        DashboardCommand::PowerOff => {
            core.power_off();
            "Powering off".into()
        }
        DashboardCommand::BrakeRelease => {
            core.brake_release();
            "Brake releasing".into()
        }
        DashboardCommand::Play => {
            if core.play() {
                "Starting program".into()
            } else {
                "Failed to execute: play".into()
            }
        }
        DashboardCommand::Stop => {
            core.stop_program("dashboard stop");
            "Stopped".into()
        }
        DashboardCommand::Pause => {
            core.pause();
            "Pausing program".into()
        }
        // The simulator has no program files on disk.
        DashboardCommand::Load(f) => format!("File not found: {f}"),
        DashboardCommand::RobotMode => robot_mode_reply(core.robot_mode()),
        DashboardCommand::SafetyMode => safety_mode_reply(core.safety_mode()),
        DashboardCommand::SafetyStatus => safety_status_reply(core.safety_mode()),
        DashboardCommand::ProgramState => {
            let (s, name) = core.program_state();
            program_state_reply(s, name)
        }
        DashboardCommand::Running => running_reply(core.program_state().0 == ProgramState::Playing),
        DashboardCommand::UnlockProtectiveStop => {
            if core.unlock_protective_stop() {
                "Protective stop releasing".into()
            } else {
                UNLOCK_TOO_EARLY.into()
            }
        }
        DashboardCommand::CloseSafetyPopup => "closing safety popup".into(),
        DashboardCommand::PolyscopeVersion => {
            let v = shared.config.controller;
            format!(
                "URSoftware {}.{}.{}.{} (Nov 22 2026)",
                v.major, v.minor, v.bugfix, v.build
            )
        }
        DashboardCommand::Quit => return ("Disconnected".into(), true),
        _ => format!("could not understand: '{}'", line.trim()),
    };
    (reply, false)
}
