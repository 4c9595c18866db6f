"""Independent Modbus RTU master (pymodbus) against the Robotiq gripper emulator.

Usage: pymodbus_gripper.py PTY_PATH
Activates the gripper (clear, then rACT, poll gSTA), closes it at full speed with FC16,
polls the status with FC04 until the fingers stop, then opens it with FC23 (read/write).
Register layout from the fact sheet: request image at 0x03E8, status image at 0x07D0, two
bytes per register, high byte first. Prints one JSON object on stdout.
"""

import json
import sys
import time

from pymodbus.client import ModbusSerialClient

SLAVE = 9


def decode_status(regs):
    b = []
    for r in regs:
        b += [r >> 8, r & 0xFF]
    return {
        "gACT": b[0] & 1,
        "gGTO": (b[0] >> 3) & 1,
        "gSTA": (b[0] >> 4) & 3,
        "gOBJ": (b[0] >> 6) & 3,
        "gFLT": b[2],
        "gPR": b[3],
        "gPO": b[4],
        "gCU": b[5],
    }


def request_regs(action, pos, speed, force):
    return [action << 8, pos, (speed << 8) | force]


def main(port):
    client = ModbusSerialClient(
        port=port, baudrate=115200, bytesize=8, parity="N", stopbits=1, timeout=1, retries=0
    )
    if not client.connect():
        raise SystemExit(f"cannot open {port}")

    def read():
        r = client.read_input_registers(0x07D0, count=3, device_id=SLAVE)
        if r.isError():
            raise RuntimeError(f"FC04 failed: {r}")
        return decode_status(r.registers)

    def write(regs):
        r = client.write_registers(0x03E8, regs, device_id=SLAVE)
        if r.isError():
            raise RuntimeError(f"FC16 failed: {r}")

    def poll(done, limit_s):
        seen = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < limit_s:
            s = read()
            seen.append(s)
            if done(s):
                return seen, time.monotonic() - t0
            time.sleep(0.02)
        raise RuntimeError(f"condition not reached in {limit_s} s; last {seen[-1]}")

    out = {}
    write(request_regs(0, 0, 0, 0))
    time.sleep(0.02)
    write(request_regs(0x01, 0, 0, 0))
    seen, out["activation_s"] = poll(lambda s: s["gSTA"] == 3, 3.0)
    out["activation_statuses"] = sorted({s["gSTA"] for s in seen})

    write(request_regs(0x09, 255, 255, 128))
    seen, out["close_s"] = poll(lambda s: s["gOBJ"] != 0 and s["gPR"] == 255, 3.0)
    out["close_positions"] = [s["gPO"] for s in seen]
    time.sleep(0.15)
    out["closed"] = read()

    r = client.readwrite_registers(
        read_address=0x07D0,
        read_count=3,
        write_address=0x03E8,
        values=request_regs(0x09, 0, 255, 128),
        device_id=SLAVE,
    )
    if r.isError():
        raise RuntimeError(f"FC23 failed: {r}")
    seen, out["open_s"] = poll(lambda s: s["gOBJ"] == 3 and s["gPR"] == 0, 3.0)
    out["opened"] = seen[-1]
    client.close()
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1])
