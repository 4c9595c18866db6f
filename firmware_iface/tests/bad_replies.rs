//! Bad bytes sent to the driver (issue 6 acceptance): a scripted gripper on a real
//! pseudo-terminal (and a scripted URCap server on loopback) answers with garbage, a wrong
//! CRC, the wrong slave id and a truncated frame; each is a typed error, never a panic, and
//! the next good answer is read correctly.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::sync::Arc;
use std::time::Duration;

use cell_types::{Clock, ManualClock};
use firmware_iface::gripper::modbus_rtu::{Response, FC_READ_INPUT};
use firmware_iface::gripper::registers::StatusImage;
use firmware_iface::gripper::transport::{ModbusRtuTransport, RegisterTransport, UrcapTransport};
use firmware_iface::gripper::{Gripper, GripperError, RobotiqGripper};
use serialport::{SerialPort, TTYPort};

#[test]
fn modbus_driver_rejects_bad_answers_then_reads_a_good_one() -> anyhow::Result<()> {
    let (mut master, mut slave) = TTYPort::pair()?;
    slave.set_timeout(Duration::from_millis(5))?;
    master.set_timeout(Duration::from_millis(500))?;
    let status = StatusImage::decode([0xB9, 0, 0, 0xFF, 0x80, 0x30]);
    let good = Response::ReadInput {
        values: status.to_registers().to_vec(),
    }
    .encode(9)?;
    let mut bad_crc = good.clone();
    bad_crc[4] ^= 1;
    let wrong_slave = Response::ReadInput {
        values: status.to_registers().to_vec(),
    }
    .encode(7)?;
    let answers: Vec<Vec<u8>> = vec![
        b"\xff\xfe garbage".to_vec(),
        bad_crc,
        wrong_slave,
        good[..6].to_vec(),
        vec![],
        good.clone(),
    ];
    // The peer hands its end back instead of closing it: a closed pty master hangs up the
    // slave side and discards what it had not yet read.
    let peer = std::thread::spawn(move || -> anyhow::Result<TTYPort> {
        for answer in answers {
            let mut req = [0u8; 8];
            master.read_exact(&mut req)?;
            anyhow::ensure!(req[0] == 9 && req[1] == FC_READ_INPUT, "request {req:02X?}");
            master.write_all(&answer)?;
        }
        Ok(master)
    });
    let mut t =
        ModbusRtuTransport::new(Box::new(slave), 9).with_reply_timeout(Duration::from_millis(60));
    let e = t.read_status().unwrap_err();
    assert!(
        matches!(
            e,
            GripperError::Malformed { .. } | GripperError::Truncated { .. }
        ),
        "{e}"
    );
    let e = t.read_status().unwrap_err();
    assert!(e.to_string().contains("CRC"), "{e}");
    let e = t.read_status().unwrap_err();
    assert!(
        matches!(
            e,
            GripperError::WrongSlave {
                expected: 9,
                got: 7
            }
        ),
        "{e}"
    );
    let e = t.read_status().unwrap_err();
    assert!(matches!(e, GripperError::Truncated { .. }), "{e}");
    let e = t.read_status().unwrap_err();
    assert!(matches!(e, GripperError::Timeout { .. }), "{e}");
    let last = t.read_status();
    peer.join()
        .map_err(|_| anyhow::anyhow!("peer panicked"))??;
    assert_eq!(last?, status);
    Ok(())
}

#[test]
fn urcap_driver_rejects_garbage_replies() -> anyhow::Result<()> {
    let listener = TcpListener::bind("127.0.0.1:0")?;
    let addr = listener.local_addr()?;
    let peer = std::thread::spawn(move || -> anyhow::Result<()> {
        let (s, _) = listener.accept()?;
        let mut w = s.try_clone()?;
        let mut r = BufReader::new(s);
        for reply in [&b"\x00\x01 what\n"[..], b"STA 999\n", b"OBJ 1\n", b"ack\n"] {
            let mut line = String::new();
            r.read_line(&mut line)?;
            w.write_all(reply)?;
        }
        Ok(())
    });
    let mut t = UrcapTransport::connect(addr, Duration::from_millis(500))?;
    assert!(matches!(
        t.write_request(&Default::default()),
        Err(GripperError::Malformed { .. })
    ));
    assert!(matches!(
        t.write_request(&Default::default()),
        Err(GripperError::Malformed { .. })
    ));
    // A well-formed reply that does not answer the question.
    assert!(matches!(
        t.write_request(&Default::default()),
        Err(GripperError::UnexpectedReply { .. })
    ));
    t.write_request(&Default::default())?;
    peer.join()
        .map_err(|_| anyhow::anyhow!("peer panicked"))??;
    Ok(())
}

#[test]
fn motion_before_activation_is_refused_without_io() -> anyhow::Result<()> {
    let (_master, slave) = TTYPort::pair()?;
    let clock: Arc<dyn Clock> = Arc::new(ManualClock::new());
    let mut g = RobotiqGripper::new(ModbusRtuTransport::new(Box::new(slave), 9), clock);
    assert!(matches!(g.open(), Err(GripperError::NotActivated)));
    let cmd = cell_types::GripperCommand::new(0.02, 0.05, 40.0)?;
    assert!(matches!(g.move_to(&cmd), Err(GripperError::NotActivated)));
    Ok(())
}

#[test]
fn activation_times_out_against_a_silent_gripper() -> anyhow::Result<()> {
    // A gripper that acknowledges writes but never finishes activating.
    let (mut master, mut slave) = TTYPort::pair()?;
    slave.set_timeout(Duration::from_millis(5))?;
    master.set_timeout(Duration::from_millis(200))?;
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop2 = stop.clone();
    let peer = std::thread::spawn(move || {
        use firmware_iface::gripper::modbus_rtu::{Direction, FrameReader, Request, Scan};
        let mut reader = FrameReader::new(Direction::Requests);
        let mut buf = [0u8; 64];
        while !stop2.load(std::sync::atomic::Ordering::SeqCst) {
            let Ok(n) = master.read(&mut buf) else {
                continue;
            };
            reader.push(&buf[..n]);
            while let Some(Scan::Frame(f)) = reader.next_scan() {
                let Ok((_, req)) = Request::decode(&f) else {
                    continue;
                };
                let resp = match req {
                    Request::WriteMultiple { start, values } => Response::WriteMultiple {
                        start,
                        count: values.len() as u16,
                    },
                    _ => Response::ReadInput {
                        values: StatusImage::decode([0x11, 0, 0, 0, 3, 0])
                            .to_registers()
                            .to_vec(),
                    },
                };
                if let Ok(bytes) = resp.encode(9) {
                    let _ = master.write_all(&bytes);
                }
            }
        }
    });
    let clock: Arc<dyn Clock> = Arc::new(ManualClock::new());
    let mut g = RobotiqGripper::new(ModbusRtuTransport::new(Box::new(slave), 9), clock.clone());
    let e = g.activate().unwrap_err();
    assert!(matches!(e, GripperError::Timeout { .. }), "{e}");
    assert!(clock.now() >= Duration::from_secs(5));
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    peer.join().map_err(|_| anyhow::anyhow!("peer panicked"))?;
    Ok(())
}

#[test]
fn urcap_late_reply_does_not_answer_the_next_command() -> anyhow::Result<()> {
    use firmware_iface::gripper::urcap::{UrcapCommand, UrcapReply, Var};
    let listener = TcpListener::bind("127.0.0.1:0")?;
    let addr = listener.local_addr()?;
    let peer = std::thread::spawn(move || -> anyhow::Result<()> {
        let (s, _) = listener.accept()?;
        let mut w = s.try_clone()?;
        let mut r = BufReader::new(s);
        let mut line = String::new();
        r.read_line(&mut line)?;
        std::thread::sleep(Duration::from_millis(150));
        w.write_all(b"ack\n")?;
        line.clear();
        r.read_line(&mut line)?;
        anyhow::ensure!(line == "GET POS\n", "{line:?}");
        w.write_all(b"POS 7\n")?;
        Ok(())
    });
    let mut t = UrcapTransport::connect(addr, Duration::from_millis(80))?;
    assert!(matches!(
        t.write_request(&Default::default()),
        Err(GripperError::Timeout { .. })
    ));
    // Let the late "ack" arrive before the next command goes out.
    std::thread::sleep(Duration::from_millis(150));
    assert_eq!(
        t.exchange(&UrcapCommand::Get(Var::Pos))?,
        UrcapReply::Value(Var::Pos, 7)
    );
    peer.join()
        .map_err(|_| anyhow::anyhow!("peer panicked"))??;
    Ok(())
}

#[test]
fn slcan_driver_rejects_bad_lines_then_reads_a_good_status() -> anyhow::Result<()> {
    use firmware_iface::gripper::can::CanMapping;
    use firmware_iface::gripper::slcan::{LineSplitter, SlcanLine};
    use firmware_iface::gripper::transport::SlcanTransport;
    let (mut master, mut slave) = TTYPort::pair()?;
    slave.set_timeout(Duration::from_millis(5))?;
    master.set_timeout(Duration::from_millis(500))?;
    let mapping = CanMapping::default();
    let status = StatusImage::decode([0xF9, 0, 0, 0x10, 0x10, 0]);
    let good = SlcanLine::Frame(mapping.status_frame(&status)).encode();
    // One answer per frame the driver sends: first only junk, then junk followed by the status.
    let mut junk = b"\x07tXYZ6\rt1236010203040506\rt18930000\r".to_vec();
    let mut second = junk.clone();
    second.extend_from_slice(&good);
    junk.extend_from_slice(&[b'9'; 40]);
    junk.push(b'\r');
    let answers = vec![junk, second];
    let peer = std::thread::spawn(move || -> anyhow::Result<TTYPort> {
        let mut splitter = LineSplitter::new();
        let mut buf = [0u8; 64];
        let mut answers = answers.into_iter();
        let mut pending = answers.next();
        while pending.is_some() {
            let n = master.read(&mut buf)?;
            let mut frames = 0;
            splitter.push(&buf[..n], |l| {
                if matches!(l, Ok(l) if l.first() == Some(&b'r') || l.first() == Some(&b't')) {
                    frames += 1;
                }
            });
            for _ in 0..frames {
                if let Some(a) = pending.take() {
                    master.write_all(&a)?;
                    pending = answers.next();
                }
            }
        }
        Ok(master)
    });
    let mut t = SlcanTransport::new(Box::new(slave), mapping)?
        .with_reply_timeout(Duration::from_millis(80));
    let e = t.read_status().unwrap_err();
    assert!(
        matches!(
            e,
            GripperError::Malformed { .. }
                | GripperError::Truncated { .. }
                | GripperError::UnexpectedReply { .. }
        ),
        "{e}"
    );
    let last = t.read_status();
    let _master = peer
        .join()
        .map_err(|_| anyhow::anyhow!("peer panicked"))??;
    assert_eq!(last?, status);
    Ok(())
}
