//! Bad bytes sent to the emulator (issue 6 acceptance): wrong CRC, truncated frames, wrong
//! slave id, garbage on the socket and on the slcan line are rejected with a logged,
//! counted reason, get no answer (Modbus, URCap) or the Lawicel error answer (slcan), and
//! the server keeps serving good requests afterwards.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::time::Duration;

use cell_types::{Clock, ManualClock};
use firmware_iface::gripper::can::CanMapping;
use firmware_iface::gripper::modbus_rtu::{Request, Response};
use firmware_iface::gripper::registers::{StatusImage, STATUS_REGISTER};
use firmware_iface::gripper::slcan::SlcanLine;
use hil_sim::gripper::{GripperSim, SimConfig};

fn sim() -> GripperSim {
    let clock: Arc<dyn Clock> = Arc::new(ManualClock::new());
    GripperSim::new(clock, SimConfig::default())
}

/// Longer than the server's frame-ending silence, so each write is judged on its own.
const GAP: Duration = Duration::from_millis(40);

fn read_all(port: &mut dyn Read) -> Vec<u8> {
    let mut out = vec![];
    let mut buf = [0u8; 256];
    while let Ok(n) = port.read(&mut buf) {
        if n == 0 {
            break;
        }
        out.extend_from_slice(&buf[..n]);
    }
    out
}

#[test]
fn modbus_slave_drops_bad_frames_and_keeps_serving() -> anyhow::Result<()> {
    let sim = sim();
    let server = sim.spawn_modbus_rtu()?;
    let path = server.pty_path().ok_or_else(|| anyhow::anyhow!("no pty"))?;
    let mut port = serialport::new(path, 115_200)
        .timeout(Duration::from_millis(60))
        .open()?;
    let read = Request::ReadInput {
        start: STATUS_REGISTER,
        count: 3,
    };
    let good = read.encode(9)?;
    let mut bad_crc = good.clone();
    bad_crc[7] ^= 0x5A;
    let other_slave = read.encode(5)?;
    let wrong_register = Request::ReadInput {
        start: 0x0100,
        count: 3,
    }
    .encode(9)?;
    let cases: [(&str, &[u8]); 5] = [
        ("garbage", &[0xDE, 0xAD, 0xBE, 0xEF, 0x00]),
        ("wrong CRC", &bad_crc),
        ("wrong slave", &other_slave),
        ("truncated", &good[..5]),
        ("unknown register", &wrong_register),
    ];
    for (what, bytes) in cases {
        let before = server.stats().rejected();
        port.write_all(bytes)?;
        std::thread::sleep(GAP);
        let answer = read_all(&mut port);
        assert!(
            answer.is_empty(),
            "{what}: the gripper answered {answer:02X?}"
        );
        assert!(
            server.stats().rejected() > before,
            "{what} was not rejected"
        );
        assert!(server.is_running());
    }
    assert!(server.stats().last_reject().contains("outside"));

    port.write_all(&good)?;
    std::thread::sleep(GAP);
    let answer = read_all(&mut port);
    let (slave, resp) = Response::decode(&answer)?;
    assert_eq!(slave, 9);
    let Response::ReadInput { values } = resp else {
        panic!("unexpected {resp:?}")
    };
    let regs: [u16; 3] = values.try_into().map_err(|v| anyhow::anyhow!("{v:?}"))?;
    assert_eq!(StatusImage::from_registers(regs), sim.observe());
    Ok(())
}

#[test]
fn urcap_server_ignores_garbage_lines() -> anyhow::Result<()> {
    let sim = sim();
    let server = sim.spawn_urcap(SocketAddr::from(([127, 0, 0, 1], 0)))?;
    let addr = server.addr().ok_or_else(|| anyhow::anyhow!("no address"))?;
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_millis(100)))?;
    let mut long = vec![b'A'; 1000];
    long.push(b'\n');
    for garbage in [
        &b"\x00\xff\xfe nonsense\n"[..],
        b"SET FOO 1\n",
        b"SET ACT 300\n",
        b"GET\n",
        &long,
    ] {
        s.write_all(garbage)?;
    }
    s.write_all(b"SET ACT 1 SPE 200\nGET SPE\n")?;
    let mut r = BufReader::new(s.try_clone()?);
    let mut line = String::new();
    r.read_line(&mut line)?;
    assert_eq!(line, "ack\n");
    line.clear();
    r.read_line(&mut line)?;
    assert_eq!(line, "SPE 200\n");
    assert!(
        server.stats().rejected() >= 5,
        "rejected {}",
        server.stats().rejected()
    );
    assert!(sim.request().activate && sim.request().speed == 200);
    // A client vanishing mid-line does not take the server down.
    s.write_all(b"SET ACT")?;
    drop(r);
    drop(s);
    let mut s2 = TcpStream::connect(addr)?;
    s2.set_read_timeout(Some(Duration::from_millis(500)))?;
    s2.write_all(b"GET STA\n")?;
    let mut line = String::new();
    BufReader::new(s2).read_line(&mut line)?;
    assert!(line.starts_with("STA "), "{line:?}");
    Ok(())
}

#[test]
fn slcan_adapter_answers_bad_lines_with_bell() -> anyhow::Result<()> {
    let sim = sim();
    let mapping = CanMapping::default();
    let server = sim.spawn_slcan(mapping)?;
    let path = server.pty_path().ok_or_else(|| anyhow::anyhow!("no pty"))?;
    let mut port = serialport::new(path, 115_200)
        .timeout(Duration::from_millis(60))
        .open()?;
    // A frame before the channel is open, then garbage, a short command frame and an
    // over-long line: each gets BELL.
    for bad in [
        &b"t2096010000000000\r"[..],
        b"O\r",
        b"Xyz\r",
        b"t2091AA\r",
        b"t20960100\r",
        &[b'7'; 60],
        b"\r",
    ] {
        port.write_all(bad)?;
    }
    std::thread::sleep(GAP);
    let answer = read_all(&mut port);
    assert_eq!(
        answer.iter().filter(|b| **b == 0x07).count(),
        4,
        "{answer:?}"
    );
    assert!(server.stats().rejected() >= 4);
    port.write_all(&SlcanLine::Frame(mapping.status_poll()).encode())?;
    std::thread::sleep(GAP);
    let answer = read_all(&mut port);
    let text = String::from_utf8(answer)?;
    assert!(text.starts_with("z\rt1896"), "{text:?}");
    Ok(())
}

#[test]
fn socketcand_server_rejects_garbage_and_keeps_serving() -> anyhow::Result<()> {
    let sim = sim();
    let mapping = CanMapping::default();
    let server = sim.spawn_socketcand(SocketAddr::from(([127, 0, 0, 1], 0)), "can0", mapping)?;
    let addr = server.addr().ok_or_else(|| anyhow::anyhow!("no address"))?;
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_millis(100)))?;
    // Frames before the handshake, junk between brackets, a bad frame and a wrong bus.
    s.write_all(b"< send 189 0 >junk< open can7 >< bogus >< open can0 >< rawmode >")?;
    s.write_all(b"< send 209 3 1 2 3 >< send 209 2 zz 1 >\xff\xfe< send 189 0 >")?;
    std::thread::sleep(GAP);
    let text = String::from_utf8(read_all(&mut s))?;
    assert!(text.starts_with("< hi >"), "{text:?}");
    assert_eq!(text.matches("< ok >").count(), 2, "{text:?}");
    assert!(text.matches("< error").count() >= 3, "{text:?}");
    assert!(
        text.trim_end().ends_with(" >") && text.contains("< frame 189 "),
        "{text:?}"
    );
    assert!(
        server.stats().rejected() >= 5,
        "rejected {}",
        server.stats().rejected()
    );
    Ok(())
}
