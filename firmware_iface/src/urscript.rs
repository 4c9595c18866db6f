//! Our URScript servo program (`urscript/servo.script`) and its register contract
//! (`urscript/CONTRACT.md`): the UR `example_control_loop` pattern from the UR fact sheet's
//! "Commanding motion" section, parameterised and recognisable from its text.

use thiserror::Error;

/// The program template, with `{CYCLE}`, `{LOOKAHEAD}`, `{GAIN}`, `{WATCHDOG}` and
/// `{STOP_DECEL}` placeholders.
pub const SERVO_TEMPLATE: &str = include_str!("urscript/servo.script");
/// The marker that identifies the contract version in the program's header line.
pub const CONTRACT_MARKER: &str = "# equact-servo-contract v1";
/// Register index of the sequence/mode word (`input_int_register_24`).
pub const SEQ_REGISTER: usize = 24;
/// First register of the six targets (`input_double_register_24..29`).
pub const TARGET_REGISTER: usize = 24;
/// Register index of the acknowledgement (`output_int_register_24`).
pub const ACK_REGISTER: usize = 24;
/// Sequence word: hold.
pub const SEQ_HOLD: i32 = 0;
/// Sequence word: stop.
pub const SEQ_STOP: i32 = -1;
/// Acknowledgement: stopped on request.
pub const ACK_STOPPED: i32 = -1;
/// Acknowledgement: stopped by the watchdog.
pub const ACK_WATCHDOG: i32 = -2;

/// Why a servo program could not be rendered or recognised.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum ScriptError {
    /// A parameter outside what the controller accepts.
    #[error("servo parameter {name} = {value} is outside [{min}, {max}]; fix the UR driver configuration")]
    Parameter {
        /// Which parameter.
        name: &'static str,
        /// Value given.
        value: f64,
        /// Lower bound.
        min: f64,
        /// Upper bound.
        max: f64,
    },
    /// The text is not our servo program, or its header is damaged.
    #[error(
        "program is not the equact servo program (contract header missing or unreadable: {detail})"
    )]
    NotServoProgram {
        /// What was missing.
        detail: String,
    },
}

/// The servo program's parameters.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct ServoParams {
    /// servoj blocking time = control period (s): 0.008 CB3, 0.002 e-Series.
    pub cycle: f64,
    /// servoj lookahead time (s), 0.03..0.2.
    pub lookahead: f64,
    /// servoj gain, 100..2000.
    pub gain: f64,
    /// Cycles without a new sequence number before the program stops the arm.
    pub watchdog_cycles: u32,
    /// stopj deceleration (rad/s²).
    pub stop_decel: f64,
}

impl Default for ServoParams {
    fn default() -> Self {
        Self {
            cycle: 0.008,
            lookahead: 0.1,
            gain: 300.0,
            watchdog_cycles: 10,
            stop_decel: 4.0,
        }
    }
}

impl ServoParams {
    /// Checks the ranges the controller accepts.
    pub fn validate(&self) -> Result<(), ScriptError> {
        let checks = [
            ("cycle", self.cycle, 0.001, 0.1),
            ("lookahead", self.lookahead, 0.03, 0.2),
            ("gain", self.gain, 100.0, 2000.0),
            (
                "watchdog_cycles",
                f64::from(self.watchdog_cycles),
                1.0,
                1000.0,
            ),
            ("stop_decel", self.stop_decel, 0.1, 40.0),
        ];
        for (name, value, min, max) in checks {
            if !(value >= min && value <= max) {
                return Err(ScriptError::Parameter {
                    name,
                    value,
                    min,
                    max,
                });
            }
        }
        Ok(())
    }

    /// The program text with these parameters.
    pub fn render(&self) -> Result<String, ScriptError> {
        self.validate()?;
        Ok(SERVO_TEMPLATE
            .replace("{CYCLE}", &format!("{}", self.cycle))
            .replace("{LOOKAHEAD}", &format!("{}", self.lookahead))
            .replace("{GAIN}", &format!("{}", self.gain))
            .replace("{WATCHDOG}", &format!("{}", self.watchdog_cycles))
            .replace("{STOP_DECEL}", &format!("{}", self.stop_decel)))
    }

    /// Recognises our program in a received script and recovers its parameters: the
    /// contract header must be present and the body must use the contract's registers.
    pub fn recognise(program: &str) -> Result<Self, ScriptError> {
        let not = |detail: &str| ScriptError::NotServoProgram {
            detail: detail.to_string(),
        };
        let header = program
            .lines()
            .map(str::trim)
            .find_map(|l| l.strip_prefix(CONTRACT_MARKER))
            .ok_or_else(|| not("no contract header line"))?;
        for needle in [
            "read_input_integer_register(24)",
            "write_output_integer_register(24",
            "read_input_float_register(29)",
            "servoj(",
            "stopj(",
        ] {
            if !program.contains(needle) {
                return Err(not(&format!("body lacks {needle}")));
            }
        }
        let mut p = ServoParams::default();
        for kv in header.split_whitespace() {
            let (k, v) = kv.split_once('=').ok_or_else(|| not(kv))?;
            let x: f64 = v.parse().map_err(|_| not(kv))?;
            match k {
                "cycle" => p.cycle = x,
                "lookahead" => p.lookahead = x,
                "gain" => p.gain = x,
                "watchdog_cycles" => {
                    if x.fract() != 0.0 || !(0.0..=f64::from(u32::MAX)).contains(&x) {
                        return Err(not(kv));
                    }
                    p.watchdog_cycles = x as u32;
                }
                "stop_decel" => p.stop_decel = x,
                _ => return Err(not(kv)),
            }
        }
        p.validate()?;
        Ok(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rendered_program_is_recognised_with_its_parameters() {
        let p = ServoParams {
            cycle: 0.002,
            lookahead: 0.05,
            gain: 1000.0,
            watchdog_cycles: 25,
            stop_decel: 6.5,
        };
        let text = p.render().unwrap();
        assert!(text.starts_with("def equact_servo():"));
        assert!(!text.contains('{'), "every placeholder substituted");
        assert!(text.contains("servoj(q, 0, 0, 0.002, 0.05, 1000)"));
        assert_eq!(ServoParams::recognise(&text).unwrap(), p);
    }

    #[test]
    fn foreign_or_damaged_programs_are_not_recognised() {
        assert!(ServoParams::recognise("def prog():\n  movej([0,0,0,0,0,0])\nend\n").is_err());
        let text = ServoParams::default().render().unwrap();
        let broken = text.replace("gain=300", "gain=lots");
        assert!(ServoParams::recognise(&broken).is_err());
        let no_stop = text.replace("stopj(", "halt(");
        assert!(ServoParams::recognise(&no_stop).is_err());
    }

    #[test]
    fn out_of_range_parameters_are_refused() {
        let p = ServoParams {
            gain: 50.0,
            ..Default::default()
        };
        assert!(matches!(
            p.render(),
            Err(ScriptError::Parameter { name: "gain", .. })
        ));
    }
}
