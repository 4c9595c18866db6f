//! The simulated UR controller's servers over real loopback TCP: dashboard state machine,
//! RTDE negotiation (v1 and v2), recipes with NOT_FOUND/IN_USE, data rate, and bad clients.

#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers may panic

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::sync::Arc;
use std::time::{Duration, Instant};

use cell_types::SystemClock;
use firmware_iface::dashboard::RobotMode;
use firmware_iface::rtde::{
    split_package, DataType, FieldType, HostMessage, Layout, ProtocolVersion, RobotMessage,
};
use hil_sim::ur_controller::{start, Fault, UrSimConfig, UrSimHandle};

fn sim(config: UrSimConfig) -> UrSimHandle {
    start(config, Arc::new(SystemClock::new())).unwrap()
}

struct Dash {
    r: BufReader<TcpStream>,
    w: TcpStream,
}

impl Dash {
    fn connect(h: &UrSimHandle) -> Dash {
        let s = TcpStream::connect((h.addr(), h.ports().dashboard)).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut d = Dash {
            r: BufReader::new(s.try_clone().unwrap()),
            w: s,
        };
        assert_eq!(d.line(), "Connected: Universal Robots Dashboard Server");
        d
    }
    fn line(&mut self) -> String {
        let mut l = String::new();
        self.r.read_line(&mut l).unwrap();
        l.trim_end().to_string()
    }
    fn ask(&mut self, cmd: &str) -> String {
        writeln!(self.w, "{cmd}").unwrap();
        self.line()
    }
    fn wait_for(&mut self, cmd: &str, want: &str) {
        let t0 = Instant::now();
        while self.ask(cmd) != want {
            assert!(
                t0.elapsed() < Duration::from_secs(5),
                "{cmd} never answered {want}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

#[test]
fn dashboard_power_on_brake_release_and_protective_stop_unlock_rule() {
    let h = sim(UrSimConfig {
        initial_mode: RobotMode::PowerOff,
        ..UrSimConfig::for_tests()
    });
    let mut d = Dash::connect(&h);
    assert_eq!(d.ask("robotmode"), "Robotmode: POWER_OFF");
    assert_eq!(d.ask("running"), "Program running: false");
    assert_eq!(d.ask("power on"), "Powering on");
    d.wait_for("robotmode", "Robotmode: IDLE");
    assert_eq!(d.ask("brake release"), "Brake releasing");
    d.wait_for("robotmode", "Robotmode: RUNNING");
    assert_eq!(d.ask("safetymode"), "Safetymode: NORMAL");
    assert_eq!(d.ask("programState"), "STOPPED <unnamed>");
    assert_eq!(d.ask("play"), "Failed to execute: play");
    assert_eq!(
        d.ask("load /programs/x.urp"),
        "File not found: /programs/x.urp"
    );
    assert!(d.ask("PolyscopeVersion").starts_with("URSoftware 3.15.7"));
    assert_eq!(d.ask("jump"), "could not understand: 'jump'");

    h.inject(Fault::ProtectiveStop);
    assert_eq!(d.ask("safetystatus"), "Safetystatus: PROTECTIVE_STOP");
    assert_eq!(
        d.ask("unlock protective stop"),
        "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking"
    );
    assert_eq!(d.ask("safetymode"), "Safetymode: PROTECTIVE_STOP");
    // The 5 s rule runs on controller time; move it on instead of waiting 5 s.
    h.with_core(|c| {
        for _ in 0..(5.1 / 0.008) as usize {
            c.step();
        }
    });
    assert_eq!(d.ask("unlock protective stop"), "Protective stop releasing");
    assert_eq!(d.ask("safetymode"), "Safetymode: NORMAL");
    assert_eq!(d.ask("power off"), "Powering off");
    assert_eq!(d.ask("robotmode"), "Robotmode: POWER_OFF");
    assert_eq!(d.ask("quit"), "Disconnected");
}

struct Rtde {
    s: TcpStream,
    buf: Vec<u8>,
    v: ProtocolVersion,
}

impl Rtde {
    fn connect(h: &UrSimHandle) -> Rtde {
        let s = TcpStream::connect((h.addr(), h.ports().rtde)).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        Rtde {
            s,
            buf: Vec::new(),
            v: ProtocolVersion::V1,
        }
    }
    fn send(&mut self, m: HostMessage) {
        self.s.write_all(&m.encode(self.v).unwrap()).unwrap();
    }
    fn recv(&mut self) -> RobotMessage {
        loop {
            if let Some((raw, n)) = split_package(&self.buf).unwrap() {
                let m = RobotMessage::decode(self.v, raw).unwrap();
                self.buf.drain(..n);
                return m;
            }
            let mut c = [0u8; 4096];
            let n = self.s.read(&mut c).unwrap();
            assert!(n > 0, "server closed");
            self.buf.extend_from_slice(&c[..n]);
        }
    }
    fn ask(&mut self, m: HostMessage) -> RobotMessage {
        self.send(m);
        self.recv()
    }
    fn negotiate(&mut self, v: ProtocolVersion) {
        assert_eq!(
            self.ask(HostMessage::RequestProtocolVersion(v.number())),
            RobotMessage::ProtocolVersionAccepted(true)
        );
        self.v = v;
    }
}

fn names(n: &[&str]) -> Vec<String> {
    n.iter().map(|s| s.to_string()).collect()
}

#[test]
fn rtde_v2_recipes_not_found_in_use_and_data_rate() {
    let h = sim(UrSimConfig::for_tests());
    let mut c = Rtde::connect(&h);
    assert_eq!(
        c.ask(HostMessage::RequestProtocolVersion(3)),
        RobotMessage::ProtocolVersionAccepted(false)
    );
    c.negotiate(ProtocolVersion::V2);
    match c.ask(HostMessage::GetControllerVersion) {
        RobotMessage::ControllerVersion(v) => assert_eq!((v.major, v.minor), (3, 15)),
        m => panic!("{m:?}"),
    }
    let r = c.ask(HostMessage::SetupOutputs {
        frequency: Some(125.0),
        names: names(&["timestamp", "actual_q", "bogus_field"]),
    });
    assert_eq!(
        r,
        RobotMessage::SetupOutputs {
            recipe_id: Some(0),
            types: vec![
                FieldType::Type(DataType::Double),
                FieldType::Type(DataType::Vector6d),
                FieldType::NotFound
            ]
        }
    );
    let RobotMessage::SetupOutputs {
        recipe_id: Some(out_id),
        ..
    } = c.ask(HostMessage::SetupOutputs {
        frequency: Some(125.0),
        names: names(&[
            "timestamp",
            "actual_q",
            "robot_mode",
            "safety_mode",
            "runtime_state",
            "",
        ]),
    })
    else {
        panic!()
    };
    assert!(out_id > 0);
    let RobotMessage::SetupInputs {
        recipe_id: in_id,
        types,
    } = c.ask(HostMessage::SetupInputs {
        names: names(&["input_int_register_24", "input_double_register_24"]),
    })
    else {
        panic!()
    };
    assert!(in_id > 0, "{types:?}");
    // A second client cannot take the same inputs.
    let mut other = Rtde::connect(&h);
    other.negotiate(ProtocolVersion::V2);
    assert_eq!(
        other.ask(HostMessage::SetupInputs {
            names: names(&["input_int_register_25", "input_int_register_24"]),
        }),
        RobotMessage::SetupInputs {
            recipe_id: 0,
            types: vec![FieldType::Type(DataType::Int32), FieldType::InUse]
        }
    );
    // Inputs written by the first client reach the controller's registers.
    let lay = Layout::new(&[DataType::Int32, DataType::Double]);
    let values = lay
        .encode_all(&[
            firmware_iface::rtde::Value::Int32(42),
            firmware_iface::rtde::Value::Double(1.5),
        ])
        .unwrap();
    c.send(HostMessage::DataPackage {
        recipe_id: in_id,
        values,
    });
    assert_eq!(c.ask(HostMessage::Start), RobotMessage::StartAccepted(true));
    let layout = Layout::new(&[
        DataType::Double,
        DataType::Vector6d,
        DataType::Int32,
        DataType::Int32,
        DataType::Uint32,
    ]);
    let t0 = Instant::now();
    let mut stamps = Vec::new();
    while stamps.len() < 63 {
        match c.recv() {
            RobotMessage::DataPackage { recipe_id, values } => {
                assert_eq!(recipe_id, Some(out_id));
                stamps.push(layout.get_f64(&values, 0).unwrap());
                assert_eq!(layout.get_i32(&values, 2).unwrap(), 7);
                assert_eq!(layout.get_i32(&values, 3).unwrap(), 1);
                assert_eq!(layout.get_u32(&values, 4).unwrap(), 1);
            }
            m => panic!("{m:?}"),
        }
    }
    let wall = t0.elapsed().as_secs_f64();
    // Controller time advances one 8 ms cycle per package: no gaps, no repeats.
    for w in stamps.windows(2) {
        assert!((w[1] - w[0] - 0.008).abs() < 1e-9, "{w:?}");
    }
    assert!(
        wall > 0.3,
        "63 packages at 125 Hz cannot arrive in {wall} s"
    );
    let regs = h.snapshot().registers;
    assert_eq!((regs.input_int[24], regs.input_double[24]), (42, 1.5));
    // Closing the owner frees its inputs.
    drop(c);
    std::thread::sleep(Duration::from_millis(100));
    match other.ask(HostMessage::SetupInputs {
        names: names(&["input_int_register_24"]),
    }) {
        RobotMessage::SetupInputs { recipe_id, .. } => assert!(recipe_id > 0),
        m => panic!("{m:?}"),
    }
}

#[test]
fn rtde_v1_has_no_recipe_ids_on_outputs_and_e_series_allows_500_hz() {
    let h = sim(UrSimConfig::for_tests().e_series());
    let mut c = Rtde::connect(&h);
    c.negotiate(ProtocolVersion::V1);
    assert_eq!(
        c.ask(HostMessage::SetupOutputs {
            frequency: None,
            names: names(&["actual_q"]),
        }),
        RobotMessage::SetupOutputs {
            recipe_id: None,
            types: vec![FieldType::Type(DataType::Vector6d)]
        }
    );
    assert_eq!(c.ask(HostMessage::Start), RobotMessage::StartAccepted(true));
    match c.recv() {
        RobotMessage::DataPackage { recipe_id, values } => {
            assert_eq!(recipe_id, None);
            assert_eq!(values.len(), 48);
        }
        m => panic!("{m:?}"),
    }
    let mut c2 = Rtde::connect(&h);
    c2.negotiate(ProtocolVersion::V2);
    match c2.ask(HostMessage::SetupOutputs {
        frequency: Some(500.0),
        names: names(&["timestamp"]),
    }) {
        RobotMessage::SetupOutputs { recipe_id, .. } => assert!(recipe_id.unwrap() > 0),
        m => panic!("{m:?}"),
    }
    // 125 Hz cap on CB3.
    let cb3 = sim(UrSimConfig::for_tests());
    let mut c3 = Rtde::connect(&cb3);
    c3.negotiate(ProtocolVersion::V2);
    c3.send(HostMessage::SetupOutputs {
        frequency: Some(500.0),
        names: names(&["timestamp"]),
    });
    assert!(matches!(c3.recv(), RobotMessage::Text(_)));
    assert!(matches!(
        c3.recv(),
        RobotMessage::SetupOutputs {
            recipe_id: Some(0),
            ..
        }
    ));
}

#[test]
fn bad_clients_lose_their_connection_and_the_server_lives_on() {
    let h = sim(UrSimConfig::for_tests());
    // Garbage bytes.
    let mut g = TcpStream::connect((h.addr(), h.ports().rtde)).unwrap();
    g.write_all(&[0x00, 0x01, 0xff, 0xff]).unwrap();
    // Oversized package.
    let mut o = TcpStream::connect((h.addr(), h.ports().rtde)).unwrap();
    o.write_all(&[0xff, 0xff, b'O']).unwrap();
    // Disconnect mid-package.
    let mut m = TcpStream::connect((h.addr(), h.ports().rtde)).unwrap();
    m.write_all(&[0x00, 0x05, b'V', 0x00]).unwrap();
    drop(m);
    for s in [&mut g, &mut o] {
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut b = [0u8; 16];
        assert_eq!(
            s.read(&mut b).unwrap_or(0),
            0,
            "server closes the bad connection"
        );
    }
    std::thread::sleep(Duration::from_millis(100));
    let log = h.log().join("\n");
    assert!(log.contains("bad package"), "{log}");
    assert!(log.contains("oversized package"), "{log}");
    assert!(log.contains("in the middle of a package"), "{log}");
    // A good client still gets served.
    let mut c = Rtde::connect(&h);
    c.negotiate(ProtocolVersion::V2);
    let mut d = Dash::connect(&h);
    assert_eq!(d.ask("robotmode"), "Robotmode: RUNNING");
}

#[test]
fn unknown_program_is_reported_and_not_run() {
    let h = sim(UrSimConfig::for_tests());
    let mut c = Rtde::connect(&h);
    c.negotiate(ProtocolVersion::V2);
    c.ask(HostMessage::SetupOutputs {
        frequency: Some(125.0),
        names: names(&["runtime_state"]),
    });
    c.ask(HostMessage::Start);
    let mut s = TcpStream::connect((h.addr(), h.ports().secondary)).unwrap();
    s.write_all(b"def other():\n  movej([0,0,0,0,0,0])\nend\n")
        .unwrap();
    let t0 = Instant::now();
    loop {
        assert!(t0.elapsed() < Duration::from_secs(5), "no text message");
        if let RobotMessage::Text(t) = c.recv() {
            assert!(t.message.contains("unknown program not run"), "{t:?}");
            break;
        }
    }
    assert_eq!(h.snapshot().runtime_state(), 1);
    // Our servo program runs.
    let prog = firmware_iface::urscript::ServoParams::default()
        .render()
        .unwrap();
    s.write_all(prog.as_bytes()).unwrap();
    let t0 = Instant::now();
    while h.snapshot().runtime_state() != 2 {
        assert!(
            t0.elapsed() < Duration::from_secs(5),
            "servo program not started"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
}
