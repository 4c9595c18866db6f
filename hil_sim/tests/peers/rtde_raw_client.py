"""Independent peer: a minimal RTDE client written from the public protocol description
(UR "Real-Time Data Exchange (RTDE) Guide"), not from our Rust codec. It negotiates the
given protocol version, sets up `timestamp,actual_q`, starts, and measures the data rate.

Usage: rtde_raw_client.py HOST PORT VERSION SECONDS
Prints one JSON line: version accepted, controller version, packages, rate (Hz), largest
controller-timestamp step and the number of gaps (steps over 1.5 periods).
"""
import json
import socket
import struct
import sys
import time

host, port, version, seconds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
s = socket.create_connection((host, port), timeout=5)
buf = b""


def send(kind, payload=b""):
    s.sendall(struct.pack(">HB", 3 + len(payload), kind) + payload)


def recv():
    global buf
    while True:
        if len(buf) >= 3:
            size, kind = struct.unpack_from(">HB", buf)
            if len(buf) >= size:
                payload = buf[3:size]
                buf = buf[size:]
                if kind == ord("M"):
                    continue
                return kind, payload
        chunk = s.recv(65536)
        if not chunk:
            raise SystemExit("server closed the connection")
        buf += chunk


send(ord("V"), struct.pack(">H", version))
kind, p = recv()
assert kind == ord("V"), kind
accepted = p[0] == 1
send(ord("v"))
kind, p = recv()
assert kind == ord("v") and len(p) == 16, (kind, len(p))
controller = struct.unpack(">IIII", p)
names = b"timestamp,actual_q"
if version == 2:
    send(ord("O"), struct.pack(">d", 125.0) + names)
else:
    send(ord("O"), names)
kind, p = recv()
assert kind == ord("O"), kind
if version == 2:
    recipe, types = p[0], p[1:].decode()
else:
    recipe, types = None, p.decode()
assert types == "DOUBLE,VECTOR6D", types
send(ord("S"))
kind, p = recv()
assert kind == ord("S") and p == b"\x01", (kind, p)

stamps = []
t0 = time.monotonic()
first_arrival = None
while time.monotonic() - t0 < seconds:
    kind, p = recv()
    if kind != ord("U"):
        continue
    if version == 2:
        assert p[0] == recipe, (p[0], recipe)
        p = p[1:]
    assert len(p) == 8 + 48, len(p)
    if first_arrival is None:
        first_arrival = time.monotonic()
    stamps.append(struct.unpack_from(">d", p)[0])
last_arrival = time.monotonic()
send(ord("P"))
steps = [b - a for a, b in zip(stamps, stamps[1:])]
print(json.dumps({
    "accepted": accepted,
    "controller": controller,
    "packages": len(stamps),
    "wall_rate_hz": (len(stamps) - 1) / (last_arrival - first_arrival),
    "controller_rate_hz": (len(stamps) - 1) / (stamps[-1] - stamps[0]),
    "max_step_s": max(steps),
    "gaps": sum(1 for d in steps if d > 1.5 / 125.0),
}), flush=True)
