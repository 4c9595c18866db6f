//! Dashboard client (TCP 29999): one command, one reply line.

use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use crate::arm::ArmError;
use crate::dashboard::{
    parse_robot_mode, parse_safety_mode, DashboardCommand, RobotMode, SafetyMode, GREETING,
};

/// A connected dashboard client.
pub struct DashboardClient {
    reader: BufReader<TcpStream>,
    writer: TcpStream,
}

fn io(source: std::io::Error) -> ArmError {
    ArmError::Io {
        service: "dashboard",
        source,
    }
}

impl DashboardClient {
    /// Connects and checks the greeting.
    pub fn connect(addr: SocketAddr, timeout: Duration) -> Result<Self, ArmError> {
        let s = TcpStream::connect_timeout(&addr, timeout).map_err(|source| ArmError::Connect {
            service: "dashboard server",
            addr,
            source,
        })?;
        s.set_read_timeout(Some(timeout)).map_err(io)?;
        let mut c = Self {
            reader: BufReader::new(s.try_clone().map_err(io)?),
            writer: s,
        };
        let greeting = c.read_line()?;
        if !greeting.starts_with(GREETING) {
            return Err(ArmError::Protocol {
                service: "dashboard",
                detail: format!(
                    "unexpected greeting {greeting:?}; is this port a UR dashboard server?"
                ),
            });
        }
        Ok(c)
    }

    fn read_line(&mut self) -> Result<String, ArmError> {
        let mut l = String::new();
        let n = self.reader.read_line(&mut l).map_err(io)?;
        if n == 0 {
            return Err(ArmError::Protocol {
                service: "dashboard",
                detail: "connection closed by the controller".into(),
            });
        }
        Ok(l.trim_end().to_string())
    }

    /// Sends a command and returns the reply line.
    pub fn command(&mut self, cmd: &DashboardCommand) -> Result<String, ArmError> {
        writeln!(self.writer, "{}", cmd.line()).map_err(io)?;
        self.read_line()
    }

    /// Robot mode.
    pub fn robot_mode(&mut self) -> Result<RobotMode, ArmError> {
        let l = self.command(&DashboardCommand::RobotMode)?;
        parse_robot_mode(&l).map_err(|e| ArmError::Protocol {
            service: "dashboard",
            detail: e.to_string(),
        })
    }

    /// Safety mode.
    pub fn safety_mode(&mut self) -> Result<SafetyMode, ArmError> {
        let l = self.command(&DashboardCommand::SafetyMode)?;
        parse_safety_mode(&l).map_err(|e| ArmError::Protocol {
            service: "dashboard",
            detail: e.to_string(),
        })
    }

    /// Powers on and releases the brakes, polling `robotmode` as UR recommends.
    pub fn power_up(&mut self, timeout: Duration) -> Result<(), ArmError> {
        if self.robot_mode()? == RobotMode::Running {
            return Ok(());
        }
        self.command(&DashboardCommand::PowerOn)?;
        self.wait_mode(&[RobotMode::Idle, RobotMode::Running], timeout)?;
        self.command(&DashboardCommand::BrakeRelease)?;
        self.wait_mode(&[RobotMode::Running], timeout)
    }

    fn wait_mode(&mut self, want: &[RobotMode], timeout: Duration) -> Result<(), ArmError> {
        let t0 = Instant::now();
        loop {
            if want.contains(&self.robot_mode()?) {
                return Ok(());
            }
            if t0.elapsed() > timeout {
                return Err(ArmError::Timeout {
                    what: "the robot mode to change after power on / brake release",
                    waited: t0.elapsed().as_secs_f64(),
                });
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// `unlock protective stop`: Ok(true) when released, Ok(false) when refused (too early).
    pub fn unlock_protective_stop(&mut self) -> Result<bool, ArmError> {
        let l = self.command(&DashboardCommand::UnlockProtectiveStop)?;
        Ok(l.starts_with("Protective stop releasing"))
    }
}
