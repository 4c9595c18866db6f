"""Independent CAN peer (python-can, slcan interface) against the gripper emulator.

Usage: python_can_gripper.py slcan PTY_PATH
       python_can_gripper.py socketcand HOST PORT
Speaks the documented CAN mapping: command frames (request image, 6 bytes) on 0x209,
status frames on 0x189; a remote frame on 0x189 (slcan) or an empty data frame on 0x189
(socketcand, which has no remote frames) polls the status. Activates, closes, and prints
the decoded status frames it received as one JSON object on stdout.
"""

import json
import sys
import time

import can

COMMAND_ID = 0x200 + 9
STATUS_ID = 0x180 + 9


def decode_status(data):
    b = list(data)
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


def main(args):
    if args[0] == "slcan":
        bus = can.Bus(interface="slcan", channel=args[1], bitrate=500000, sleep_after_open=0)
        remote_poll = True
    else:
        bus = can.Bus(interface="socketcand", channel="can0", host=args[1], port=int(args[2]))
        remote_poll = False
    frames = []

    def recv_status():
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline:
            msg = bus.recv(timeout=0.2)
            if msg is None:
                continue
            frames.append(
                {"id": msg.arbitration_id, "dlc": msg.dlc, "remote": msg.is_remote_frame}
            )
            if msg.arbitration_id == STATUS_ID and not msg.is_remote_frame:
                if msg.dlc != 6:
                    raise RuntimeError(f"status frame with dlc {msg.dlc}")
                return decode_status(msg.data)
        raise RuntimeError("no status frame within 1 s")

    def command(action, pos, speed, force):
        bus.send(
            can.Message(
                arbitration_id=COMMAND_ID,
                is_extended_id=False,
                data=[action, 0, 0, pos, speed, force],
            )
        )
        return recv_status()

    def poll():
        if remote_poll:
            msg = can.Message(
                arbitration_id=STATUS_ID, is_extended_id=False, is_remote_frame=True, dlc=6
            )
        else:
            msg = can.Message(arbitration_id=STATUS_ID, is_extended_id=False, data=[])
        bus.send(msg)
        return recv_status()

    def wait(done, limit_s):
        t0 = time.monotonic()
        while time.monotonic() - t0 < limit_s:
            s = poll()
            if done(s):
                return s
            time.sleep(0.02)
        raise RuntimeError(f"condition not reached in {limit_s} s")

    out = {}
    out["after_clear"] = command(0, 0, 0, 0)
    time.sleep(0.02)
    command(0x01, 0, 0, 0)
    out["activated"] = wait(lambda s: s["gSTA"] == 3, 3.0)
    command(0x09, 255, 255, 200)
    out["closed"] = wait(lambda s: s["gOBJ"] != 0 and s["gPR"] == 255, 3.0)
    out["frame_ids"] = sorted({f["id"] for f in frames})
    bus.shutdown()
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1:])
