//! Dashboard server (TCP 29999) line codec with no I/O: commands the host sends and the
//! replies the controller answers, newline-terminated text, as listed in the UR fact sheet's
//! "Dashboard server" table (UR dashboard server manual, CB3 3.x).

use thiserror::Error;

/// The greeting the controller sends on connect.
pub const GREETING: &str = "Connected: Universal Robots Dashboard Server";
/// The refusal text for unlocking a protective stop less than 5 s after it happened.
pub const UNLOCK_TOO_EARLY: &str = "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking";

/// Why a dashboard line could not be parsed.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum DashboardError {
    /// A command the dashboard server does not know.
    #[error(
        "unknown dashboard command {line:?}; see the dashboard server manual for the command list"
    )]
    UnknownCommand {
        /// The line received.
        line: String,
    },
    /// A reply that does not have the expected shape.
    #[error("unexpected dashboard reply {line:?} to {command:?}; the controller software may be too old or another program answered")]
    UnexpectedReply {
        /// The command sent.
        command: String,
        /// The line received.
        line: String,
    },
}

/// Robot mode as the controller names it (RTDE `robot_mode` numbers in [`RobotMode::code`]).
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum RobotMode {
    /// -1.
    NoController,
    /// 0.
    Disconnected,
    /// 1.
    ConfirmSafety,
    /// 2.
    Booting,
    /// 3.
    PowerOff,
    /// 4.
    PowerOn,
    /// 5: powered, brakes engaged.
    Idle,
    /// 6.
    Backdrive,
    /// 7: brakes released, ready to move.
    Running,
}

impl RobotMode {
    const TABLE: [(RobotMode, i32, &'static str); 9] = [
        (RobotMode::NoController, -1, "NO_CONTROLLER"),
        (RobotMode::Disconnected, 0, "DISCONNECTED"),
        (RobotMode::ConfirmSafety, 1, "CONFIRM_SAFETY"),
        (RobotMode::Booting, 2, "BOOTING"),
        (RobotMode::PowerOff, 3, "POWER_OFF"),
        (RobotMode::PowerOn, 4, "POWER_ON"),
        (RobotMode::Idle, 5, "IDLE"),
        (RobotMode::Backdrive, 6, "BACKDRIVE"),
        (RobotMode::Running, 7, "RUNNING"),
    ];

    /// RTDE `robot_mode` number.
    pub fn code(self) -> i32 {
        Self::TABLE.iter().find(|e| e.0 == self).map_or(-1, |e| e.1)
    }

    /// From an RTDE `robot_mode` number.
    pub fn from_code(code: i32) -> Option<Self> {
        Self::TABLE.iter().find(|e| e.1 == code).map(|e| e.0)
    }

    /// Dashboard name.
    pub fn name(self) -> &'static str {
        Self::TABLE
            .iter()
            .find(|e| e.0 == self)
            .map_or("NO_CONTROLLER", |e| e.2)
    }

    /// From a dashboard name.
    pub fn from_name(s: &str) -> Option<Self> {
        Self::TABLE.iter().find(|e| e.2 == s).map(|e| e.0)
    }
}

/// Safety mode (RTDE `safety_mode` numbers in [`SafetyMode::code`]).
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum SafetyMode {
    /// 1.
    Normal,
    /// 2.
    Reduced,
    /// 3.
    ProtectiveStop,
    /// 4.
    Recovery,
    /// 5.
    SafeguardStop,
    /// 6.
    SystemEmergencyStop,
    /// 7.
    RobotEmergencyStop,
    /// 8.
    Violation,
    /// 9.
    Fault,
}

impl SafetyMode {
    const TABLE: [(SafetyMode, i32, &'static str); 9] = [
        (SafetyMode::Normal, 1, "NORMAL"),
        (SafetyMode::Reduced, 2, "REDUCED"),
        (SafetyMode::ProtectiveStop, 3, "PROTECTIVE_STOP"),
        (SafetyMode::Recovery, 4, "RECOVERY"),
        (SafetyMode::SafeguardStop, 5, "SAFEGUARD_STOP"),
        (SafetyMode::SystemEmergencyStop, 6, "SYSTEM_EMERGENCY_STOP"),
        (SafetyMode::RobotEmergencyStop, 7, "ROBOT_EMERGENCY_STOP"),
        (SafetyMode::Violation, 8, "VIOLATION"),
        (SafetyMode::Fault, 9, "FAULT"),
    ];

    /// RTDE `safety_mode` number.
    pub fn code(self) -> i32 {
        Self::TABLE.iter().find(|e| e.0 == self).map_or(9, |e| e.1)
    }

    /// From an RTDE `safety_mode` number.
    pub fn from_code(code: i32) -> Option<Self> {
        Self::TABLE.iter().find(|e| e.1 == code).map(|e| e.0)
    }

    /// Dashboard name.
    pub fn name(self) -> &'static str {
        Self::TABLE
            .iter()
            .find(|e| e.0 == self)
            .map_or("FAULT", |e| e.2)
    }

    /// From a dashboard name.
    pub fn from_name(s: &str) -> Option<Self> {
        Self::TABLE.iter().find(|e| e.2 == s).map(|e| e.0)
    }

    /// True for either emergency stop.
    pub fn is_emergency_stop(self) -> bool {
        matches!(
            self,
            SafetyMode::SystemEmergencyStop | SafetyMode::RobotEmergencyStop
        )
    }
}

/// A dashboard command line.
#[derive(Clone, Debug, PartialEq, Eq)]
#[non_exhaustive]
pub enum DashboardCommand {
    /// `power on`.
    PowerOn,
    /// `power off`.
    PowerOff,
    /// `brake release`.
    BrakeRelease,
    /// `play`.
    Play,
    /// `stop`.
    Stop,
    /// `pause`.
    Pause,
    /// `load <file>`.
    Load(String),
    /// `robotmode`.
    RobotMode,
    /// `safetymode`.
    SafetyMode,
    /// `safetystatus`.
    SafetyStatus,
    /// `programState`.
    ProgramState,
    /// `running`.
    Running,
    /// `unlock protective stop`.
    UnlockProtectiveStop,
    /// `close safety popup`.
    CloseSafetyPopup,
    /// `PolyscopeVersion`.
    PolyscopeVersion,
    /// `quit`.
    Quit,
}

impl DashboardCommand {
    /// The line to send, without the newline.
    pub fn line(&self) -> String {
        match self {
            DashboardCommand::PowerOn => "power on".into(),
            DashboardCommand::PowerOff => "power off".into(),
            DashboardCommand::BrakeRelease => "brake release".into(),
            DashboardCommand::Play => "play".into(),
            DashboardCommand::Stop => "stop".into(),
            DashboardCommand::Pause => "pause".into(),
            DashboardCommand::Load(f) => format!("load {f}"),
            DashboardCommand::RobotMode => "robotmode".into(),
            DashboardCommand::SafetyMode => "safetymode".into(),
            DashboardCommand::SafetyStatus => "safetystatus".into(),
            DashboardCommand::ProgramState => "programState".into(),
            DashboardCommand::Running => "running".into(),
            DashboardCommand::UnlockProtectiveStop => "unlock protective stop".into(),
            DashboardCommand::CloseSafetyPopup => "close safety popup".into(),
            DashboardCommand::PolyscopeVersion => "PolyscopeVersion".into(),
            DashboardCommand::Quit => "quit".into(),
        }
    }

    /// Parses a received line (trailing `\r`/`\n` and surrounding blanks ignored; the
    /// controller matches commands case-sensitively except for `programState`/`PolyscopeVersion`
    /// which clients also send lower-case).
    pub fn parse(line: &str) -> Result<Self, DashboardError> {
        let l = line.trim();
        Ok(match l {
            "power on" => DashboardCommand::PowerOn,
            "power off" => DashboardCommand::PowerOff,
            "brake release" => DashboardCommand::BrakeRelease,
            "play" => DashboardCommand::Play,
            "stop" => DashboardCommand::Stop,
            "pause" => DashboardCommand::Pause,
            "robotmode" => DashboardCommand::RobotMode,
            "safetymode" => DashboardCommand::SafetyMode,
            "safetystatus" => DashboardCommand::SafetyStatus,
            "running" => DashboardCommand::Running,
            "unlock protective stop" => DashboardCommand::UnlockProtectiveStop,
            "close safety popup" => DashboardCommand::CloseSafetyPopup,
            "quit" => DashboardCommand::Quit,
            _ if l.eq_ignore_ascii_case("programState") => DashboardCommand::ProgramState,
            _ if l.eq_ignore_ascii_case("PolyscopeVersion") => DashboardCommand::PolyscopeVersion,
            _ => match l.strip_prefix("load ") {
                Some(f) if !f.trim().is_empty() => DashboardCommand::Load(f.trim().to_string()),
                _ => {
                    return Err(DashboardError::UnknownCommand {
                        line: l.to_string(),
                    })
                }
            },
        })
    }
}

/// Program state as `programState` reports it.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum ProgramState {
    /// `STOPPED`.
    Stopped,
    /// `PLAYING`.
    Playing,
    /// `PAUSED`.
    Paused,
}

impl ProgramState {
    /// Wire name.
    pub fn name(self) -> &'static str {
        match self {
            ProgramState::Stopped => "STOPPED",
            ProgramState::Playing => "PLAYING",
            ProgramState::Paused => "PAUSED",
        }
    }
}

/// Reply line to `robotmode`.
pub fn robot_mode_reply(m: RobotMode) -> String {
    format!("Robotmode: {}", m.name())
}

/// Reply line to `safetymode`.
pub fn safety_mode_reply(m: SafetyMode) -> String {
    format!("Safetymode: {}", m.name())
}

/// Reply line to `safetystatus`.
pub fn safety_status_reply(m: SafetyMode) -> String {
    format!("Safetystatus: {}", m.name())
}

/// Reply line to `programState`.
pub fn program_state_reply(s: ProgramState, program: &str) -> String {
    format!("{} {program}", s.name())
}

/// Reply line to `running`.
pub fn running_reply(running: bool) -> String {
    format!("Program running: {running}")
}

/// Parses a `robotmode` reply.
pub fn parse_robot_mode(line: &str) -> Result<RobotMode, DashboardError> {
    line.trim()
        .strip_prefix("Robotmode: ")
        .and_then(RobotMode::from_name)
        .ok_or_else(|| DashboardError::UnexpectedReply {
            command: "robotmode".into(),
            line: line.to_string(),
        })
}

/// Parses a `safetymode` or `safetystatus` reply.
pub fn parse_safety_mode(line: &str) -> Result<SafetyMode, DashboardError> {
    let l = line.trim();
    l.strip_prefix("Safetymode: ")
        .or_else(|| l.strip_prefix("Safetystatus: "))
        .and_then(SafetyMode::from_name)
        .ok_or_else(|| DashboardError::UnexpectedReply {
            command: "safetymode".into(),
            line: line.to_string(),
        })
}

/// Parses a `running` reply.
pub fn parse_running(line: &str) -> Result<bool, DashboardError> {
    match line.trim() {
        "Program running: true" => Ok(true),
        "Program running: false" => Ok(false),
        _ => Err(DashboardError::UnexpectedReply {
            command: "running".into(),
            line: line.to_string(),
        }),
    }
}

/// Parses a `programState` reply into the state and program name.
pub fn parse_program_state(line: &str) -> Result<(ProgramState, String), DashboardError> {
    let l = line.trim();
    let (s, name) = l.split_once(' ').unwrap_or((l, ""));
    let state = match s {
        "STOPPED" => ProgramState::Stopped,
        "PLAYING" => ProgramState::Playing,
        "PAUSED" => ProgramState::Paused,
        _ => {
            return Err(DashboardError::UnexpectedReply {
                command: "programState".into(),
                line: line.to_string(),
            })
        }
    };
    Ok((state, name.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_round_trip_through_their_lines() {
        for c in [
            DashboardCommand::PowerOn,
            DashboardCommand::PowerOff,
            DashboardCommand::BrakeRelease,
            DashboardCommand::Play,
            DashboardCommand::Stop,
            DashboardCommand::Pause,
            DashboardCommand::Load("/programs/a.urp".into()),
            DashboardCommand::RobotMode,
            DashboardCommand::SafetyMode,
            DashboardCommand::SafetyStatus,
            DashboardCommand::ProgramState,
            DashboardCommand::Running,
            DashboardCommand::UnlockProtectiveStop,
            DashboardCommand::CloseSafetyPopup,
            DashboardCommand::PolyscopeVersion,
            DashboardCommand::Quit,
        ] {
            assert_eq!(
                DashboardCommand::parse(&format!("{}\r\n", c.line())).unwrap(),
                c
            );
        }
        assert_eq!(DashboardCommand::PowerOn.line(), "power on");
        assert_eq!(
            DashboardCommand::UnlockProtectiveStop.line(),
            "unlock protective stop"
        );
        assert!(matches!(
            DashboardCommand::parse("fly away"),
            Err(DashboardError::UnknownCommand { .. })
        ));
        assert!(DashboardCommand::parse("load ").is_err());
    }

    #[test]
    fn replies_match_the_fact_sheet_and_parse_back() {
        assert_eq!(
            robot_mode_reply(RobotMode::PowerOff),
            "Robotmode: POWER_OFF"
        );
        assert_eq!(safety_mode_reply(SafetyMode::Normal), "Safetymode: NORMAL");
        assert_eq!(
            safety_status_reply(SafetyMode::ProtectiveStop),
            "Safetystatus: PROTECTIVE_STOP"
        );
        assert_eq!(running_reply(true), "Program running: true");
        assert_eq!(
            program_state_reply(ProgramState::Playing, "equact_servo"),
            "PLAYING equact_servo"
        );
        assert_eq!(
            parse_robot_mode("Robotmode: RUNNING\n").unwrap(),
            RobotMode::Running
        );
        assert_eq!(
            parse_safety_mode("Safetystatus: ROBOT_EMERGENCY_STOP").unwrap(),
            SafetyMode::RobotEmergencyStop
        );
        assert!(!parse_running("Program running: false").unwrap());
        assert_eq!(
            parse_program_state("STOPPED <unnamed>").unwrap(),
            (ProgramState::Stopped, "<unnamed>".to_string())
        );
        assert!(parse_robot_mode("Robotmode: FLYING").is_err());
        assert!(parse_safety_mode("nonsense").is_err());
    }

    #[test]
    fn mode_codes_match_rtde_numbers() {
        assert_eq!(RobotMode::Running.code(), 7);
        assert_eq!(RobotMode::PowerOff.code(), 3);
        assert_eq!(RobotMode::from_code(5), Some(RobotMode::Idle));
        assert_eq!(SafetyMode::ProtectiveStop.code(), 3);
        assert_eq!(SafetyMode::from_code(1), Some(SafetyMode::Normal));
        assert_eq!(SafetyMode::from_code(42), None);
        assert!(SafetyMode::RobotEmergencyStop.is_emergency_stop());
    }
}
