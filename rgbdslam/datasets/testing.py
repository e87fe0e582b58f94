"""Test data for the readers: real ROS bags (ROS 1, ROS 2 sqlite3/mcap, RealSense SDK layout)
written from a TUM folder with ``rosbags``' own writers, for the bag reader's tests and the
own-data benchmark. Every kind keeps the TUM images' values exactly (lossless PNG compression,
depth units chosen so the raw values survive), so a run on the bag can be compared with the run
on the folder bit for bit."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from rosbags.typesys import Stores, get_typestore

from rgbdslam.datasets.tum import TumSequence, read_file_list
from rgbdslam.evaluation.associate import associate

TUM_SCALE = 5000.0


def _pairs(src: Path, n: int | None):
    ts_rgb, f_rgb = read_file_list(src / "rgb.txt")
    ts_d, f_d = read_file_list(src / "depth.txt")
    ia, ib = associate(ts_rgb, ts_d, 0.02, 0.0)
    ia, ib = ia[:n], ib[:n]
    return [(ts_rgb[i], src / f_rgb[i], ts_d[j], src / f_d[j]) for i, j in zip(ia, ib)]


def _time(ts, t: float):
    sec = int(np.floor(t))
    return ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)))


def _header(ts, t: float, frame: str, ros1: bool):
    H = ts.types["std_msgs/msg/Header"]
    return H(seq=0, stamp=_time(ts, t), frame_id=frame) if ros1 else H(stamp=_time(ts, t), frame_id=frame)


def _image(ts, t, frame, img: np.ndarray, encoding: str, ros1: bool):
    h, w = img.shape[:2]
    data = np.ascontiguousarray(img).view(np.uint8).reshape(-1)
    return ts.types["sensor_msgs/msg/Image"](header=_header(ts, t, frame, ros1), height=h, width=w, encoding=encoding,
                                            is_bigendian=0, step=data.size // h, data=data)


def _compressed(ts, t, frame, data: bytes, fmt: str, ros1: bool):
    return ts.types["sensor_msgs/msg/CompressedImage"](header=_header(ts, t, frame, ros1), format=fmt,
                                                      data=np.frombuffer(data, np.uint8))


def _info(ts, t, frame, cam, ros1: bool):
    RegionOfInterest = ts.types["sensor_msgs/msg/RegionOfInterest"]
    K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1.0])
    R = np.eye(3).reshape(-1)
    P = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1.0, 0])
    D = np.array(cam.dist, dtype=np.float64)
    kw = dict(header=_header(ts, t, frame, ros1), height=cam.height, width=cam.width, distortion_model="plumb_bob",
              binning_x=0, binning_y=0,
              roi=RegionOfInterest(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    kw.update(dict(D=D, K=K, R=R, P=P) if ros1 else dict(d=D, k=K, r=R, p=P))
    return ts.types["sensor_msgs/msg/CameraInfo"](**kw)


def write_bag(src: Path, out: Path, kind: str = "ros1", color: str = "rgb8", depth: str = "16UC1",
              frames: int | None = None, camera_info: bool = True, extra_color_topic: bool = False,
              depth_info_camera=None, depth_to_color: np.ndarray | None = None, color_info_camera=None) -> Path:
    """Write the first ``frames`` colour/depth pairs of the TUM folder ``src`` into a bag at ``out``.

    kind: ``ros1`` (.bag), ``ros2`` (sqlite3 folder), ``mcap`` (ROS 2 mcap folder), ``realsense``
    (ROS 1 bag in the RealSense SDK's topic layout, mono16 depth with its 'Depth Units').
    color: ``rgb8``, ``bgr8`` or ``png`` (CompressedImage). depth: ``16UC1`` (raw TUM units: read
    it with dataset.depth_scale=5000), ``32FC1`` (metres), ``compressedDepth`` (16UC1 PNG, raw
    units), ``none`` (no depth topic) or ``yuv422`` (an encoding the reader does not know).
    """
    src, out = Path(src), Path(out)
    cam = TumSequence(src).camera
    ros1 = kind in ("ros1", "realsense")
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if kind == "realsense":
        t_color, t_depth = "/device_0/sensor_1/Color_0/image/data", "/device_0/sensor_0/Depth_0/image/data"
        i_color, i_depth = "/device_0/sensor_1/Color_0/info/camera_info", "/device_0/sensor_0/Depth_0/info/camera_info"
    else:
        t_color, t_depth = "/camera/color/image_raw", "/camera/depth/image_raw"
        i_color, i_depth = "/camera/color/camera_info", "/camera/depth/camera_info"
    if color == "png":
        t_color += "/compressed"
    if depth == "compressedDepth":
        t_depth += "/compressedDepth"
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(out)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(out, version=9,
                        storage_plugin=StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3)
    msgs = []  # (topic, msgtype, t, msg)
    for t_rgb, f_rgb, t_d, f_d in _pairs(src, frames):
        bgr = cv2.imread(str(f_rgb), cv2.IMREAD_COLOR)
        raw = cv2.imread(str(f_d), cv2.IMREAD_UNCHANGED)
        if color == "png":
            ok, buf = cv2.imencode(".png", bgr)
            msgs.append((t_color, "sensor_msgs/msg/CompressedImage", t_rgb,
                         _compressed(ts, t_rgb, "color", buf.tobytes(), "rgb8; png compressed bgr8", ros1)))
        else:
            img = bgr if color == "bgr8" else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            msgs.append((t_color, "sensor_msgs/msg/Image", t_rgb, _image(ts, t_rgb, "color", img, color, ros1)))
            if extra_color_topic:
                msgs.append(("/camera/ir/image_raw", "sensor_msgs/msg/Image", t_rgb,
                             _image(ts, t_rgb, "ir", img, color, ros1)))
        if depth == "none":
            pass
        elif depth == "compressedDepth":
            ok, buf = cv2.imencode(".png", raw)
            data = np.zeros(3, "<f4").tobytes() + buf.tobytes()  # the transport's 12-byte header, then PNG
            msgs.append((t_depth, "sensor_msgs/msg/CompressedImage", t_d,
                         _compressed(ts, t_d, "depth", data, "16UC1; compressedDepth png", ros1)))
        else:
            if depth == "32FC1":
                img, enc = raw.astype(np.float32) * np.float32(1.0 / TUM_SCALE), "32FC1"
            elif depth == "yuv422":
                img, enc = raw, "yuv422"
            else:
                img, enc = raw, ("mono16" if kind == "realsense" else depth)
            msgs.append((t_depth, "sensor_msgs/msg/Image", t_d, _image(ts, t_d, "depth", img, enc, ros1)))
    first = min(m[2] for m in msgs)
    if camera_info:
        msgs.append((i_color, "sensor_msgs/msg/CameraInfo", first,
                     _info(ts, first, "color", color_info_camera or cam, ros1)))
        msgs.append((i_depth, "sensor_msgs/msg/CameraInfo", first,
                     _info(ts, first, "depth", depth_info_camera or cam, ros1)))
    if kind == "realsense":
        Float32 = ts.types["std_msgs/msg/Float32"]
        msgs.append(("/device_0/sensor_0/option/Depth Units/value", "std_msgs/msg/Float32", first,
                     Float32(data=1.0 / TUM_SCALE)))
        Tr, V3, Q = (ts.types[f"geometry_msgs/msg/{n}"] for n in ("Transform", "Vector3", "Quaternion"))
        from scipy.spatial.transform import Rotation

        # each stream's extrinsic from the reference stream (depth), as the SDK writes it
        for topic, T in (("/device_0/sensor_0/Depth_0/tf/0", np.eye(4)),
                         ("/device_0/sensor_1/Color_0/tf/0", depth_to_color if depth_to_color is not None else np.eye(4))):
            q = Rotation.from_matrix(T[:3, :3]).as_quat()
            msgs.append((topic, "geometry_msgs/msg/Transform", first,
                         Tr(translation=V3(x=T[0, 3], y=T[1, 3], z=T[2, 3]), rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3]))))
    msgs.sort(key=lambda m: m[2])
    with writer:
        conns = {}
        for topic, msgtype, _, _ in msgs:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for topic, msgtype, t, msg in msgs:
            data = ts.serialize_ros1(msg, msgtype) if ros1 else ts.serialize_cdr(msg, msgtype)
            writer.write(conns[topic], int(round(t * 1e9)), data)
    return out


def write_realsense_recording(src: Path, out: Path, frames: int | None = None) -> Path:
    """Record the first ``frames`` colour/depth pairs of the TUM folder ``src`` with the RealSense
    SDK's own recorder (``pyrealsense2``: a software device fed with the TUM images, the colour
    and depth streams registered, depth units 1/5000 m). SDK 2.57+ writes a lone ROS 2 ``.db3``."""
    import time

    import pyrealsense2 as rs

    cam = TumSequence(src).camera
    dev = rs.software_device()
    sensors, profiles = [], []
    for name, stream, fmt, bpp, uid in (("Depth", rs.stream.depth, rs.format.z16, 2, 0),
                                        ("Color", rs.stream.color, rs.format.rgb8, 3, 1)):
        intr = rs.intrinsics()
        intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy
        intr.model, intr.coeffs = rs.distortion.brown_conrady, list(cam.dist)
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid, vs.width, vs.height, vs.fps, vs.bpp, vs.fmt, vs.intrinsics = (
            stream, 0, uid, cam.width, cam.height, 30, bpp, fmt, intr)
        s = dev.add_sensor(name)
        profiles.append(s.add_video_stream(vs))
        sensors.append(s)
    sensors[0].add_read_only_option(rs.option.depth_units, 1.0 / TUM_SCALE)
    same = rs.extrinsics()
    same.rotation, same.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    profiles[0].register_extrinsics_to(profiles[1], same)
    profiles[1].register_extrinsics_to(profiles[0], same)
    rec = rs.recorder(str(out), dev)
    rec_sensors = rec.query_sensors()
    got = []
    for s, p in zip(rec_sensors, profiles):
        s.open(p)
        s.start(lambda f: got.append(1))
    keep = []
    pairs = _pairs(src, frames)
    for k, (t_rgb, f_rgb, t_d, f_d) in enumerate(pairs):
        rgb = cv2.cvtColor(cv2.imread(str(f_rgb), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        raw = cv2.imread(str(f_d), cv2.IMREAD_UNCHANGED)
        for s, p, img, bpp, t in ((sensors[0], profiles[0], raw, 2, t_d), (sensors[1], profiles[1], rgb, 3, t_rgb)):
            f = rs.software_video_frame()
            buf = np.ascontiguousarray(img)
            keep.append(buf)
            f.pixels, f.bpp, f.stride, f.timestamp = buf, bpp, cam.width * bpp, t * 1000.0
            f.domain, f.frame_number, f.profile = rs.timestamp_domain.system_time, k, p.as_video_stream_profile()
            s.on_video_frame(f)
        deadline = time.monotonic() + 10
        while len(got) < 2 * (k + 1) and time.monotonic() < deadline:  # let the recorder take them in order
            time.sleep(0.005)
    for s in rec_sensors:
        s.stop()
        s.close()
    del rec_sensors, rec
    return out
