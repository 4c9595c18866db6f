"""Writes a small RealSense recording (.bag) with librealsense's own recorder, for the Rust
D455 backend's playback test: a software device (pyrealsense2.software_device) with one
sensor streaming depth (Z16) and left IR (Y8, infrared index 1) at known intrinsics and
depth units UNITS (m per raw count). Frame i holds depth(u, v) = 500 + 3 u + 7 v + 11 i
(millimetres; raw = mm * 0.001 / UNITS) and
ir(u, v) = (u + 2 v + 5 i) mod 256, so every pixel of every frame is checkable.

With a seventh argument `colour`, a second sensor streams RGB8 at the same size and
intrinsics, registered with identity extrinsics to depth, with
rgb(u, v) = ((3 u + i) mod 256, (5 v) mod 256, (u + v + 7 i) mod 256).

Usage: realsense_bag.py OUT.db3 WIDTH HEIGHT FPS FRAMES UNITS [colour]
(librealsense 2.59 records ROS 2 .db3 files; its recorder refuses any other extension.)
Prints one JSON line: {"librealsense": version, "frames": n, "intrinsics": {...}}.
"""

import ctypes
import json
import sys


def load_pyrealsense2():
    # The wheel links libusb-1.0.so.0 dynamically; the libusb-package wheel ships it.
    # Loading it first (global) lets the dynamic linker resolve the dependency by soname.
    import libusb_package

    path = libusb_package.get_library_path()
    ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    import pyrealsense2

    return pyrealsense2


def main():
    out, width, height, fps, frames = sys.argv[1], *map(int, sys.argv[2:6])
    units = float(sys.argv[6])
    colour = len(sys.argv) > 7 and sys.argv[7] == "colour"
    per_mm = 0.001 / units
    rs = load_pyrealsense2()
    import numpy as np

    intr = rs.intrinsics()
    intr.width, intr.height = width, height
    intr.fx, intr.fy = 421.25, 420.75
    intr.ppx, intr.ppy = width / 2 - 0.5 + 1.25, height / 2 - 0.5 - 0.75
    intr.model = rs.distortion.none
    intr.coeffs = [0.0, 0.0, 0.0, 0.0, 0.0]

    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, "Intel RealSense D455 (software)")
    dev.register_info(rs.camera_info.serial_number, "000000000001")
    sensor = dev.add_sensor("Stereo Module")

    def stream(kind, index, uid, fmt, bpp, sensor=sensor):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, index, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = width, height, fps, bpp, fmt
        vs.intrinsics = intr
        return sensor.add_video_stream(vs)

    depth_profile = stream(rs.stream.depth, 0, 0, rs.format.z16, 2)
    ir_profile = stream(rs.stream.infrared, 1, 1, rs.format.y8, 1)
    sensor.add_read_only_option(rs.option.depth_units, units)
    if colour:
        colour_sensor = dev.add_sensor("RGB Camera")
        colour_profile = stream(rs.stream.color, 0, 2, rs.format.rgb8, 3, colour_sensor)
        identity = rs.extrinsics()
        identity.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        identity.translation = [0.0, 0.0, 0.0]
        depth_profile.register_extrinsics_to(colour_profile, identity)
        ir_profile.register_extrinsics_to(colour_profile, identity)

    recorder = rs.recorder(out, dev)
    sensor.open([depth_profile, ir_profile])
    sensor.start(lambda f: None)
    if colour:
        colour_sensor.open(colour_profile)
        colour_sensor.start(lambda f: None)
    u = np.arange(width)[None, :]
    v = np.arange(height)[:, None]
    keep = []
    for i in range(frames):
        depth = np.rint((500 + 3 * u + 7 * v + 11 * i) * per_mm).astype(np.uint16)
        ir = ((u + 2 * v + 5 * i) % 256).astype(np.uint8)
        streams = [(sensor, depth_profile, depth, 2), (sensor, ir_profile, ir, 1)]
        if colour:
            rgb = np.stack(
                [
                    np.broadcast_to((3 * u + i) % 256, (height, width)),
                    np.broadcast_to((5 * v) % 256, (height, width)),
                    (u + v + 7 * i) % 256,
                ],
                axis=-1,
            ).astype(np.uint8)
            streams.append((colour_sensor, colour_profile, np.ascontiguousarray(rgb), 3))
        for target, profile, pixels, bpp in streams:
            f = rs.software_video_frame()
            f.pixels = pixels
            f.bpp = bpp
            f.stride = width * bpp
            f.timestamp = i * 1000.0 / fps
            f.domain = rs.timestamp_domain.hardware_clock
            f.frame_number = i
            f.profile = profile.as_video_stream_profile()
            if bpp == 2:
                f.depth_units = units
            keep.append(pixels)
            target.on_video_frame(f)
    sensor.stop()
    sensor.close()
    if colour:
        colour_sensor.stop()
        colour_sensor.close()
    del recorder
    print(json.dumps({
        "librealsense": rs.__version__,
        "frames": frames,
        "depth_units": units,
        "colour": colour,
        "intrinsics": {"width": width, "height": height, "fx": intr.fx, "fy": intr.fy,
                       "ppx": intr.ppx, "ppy": intr.ppy},
    }))


if __name__ == "__main__":
    main()
