"""ROS bag reader: ROS 1 ``.bag``, ROS 2 bag folders (``metadata.yaml`` with ``.db3`` or
``.mcap``) and RealSense SDK recordings (topics ``/device_0/sensor_N/...``: ROS 1 ``.bag`` from
SDK versions before 2.57, a lone ROS 2 ``.db3`` from 2.57 on), through the ``rosbags`` library
(pure Python, no ROS installation).

Messages: colour and depth as ``sensor_msgs/Image`` (colour ``rgb8 bgr8 rgba8 bgra8 mono8``;
depth ``16UC1``/``mono16`` in millimetres, or the RealSense recording's ``Depth Units``, and
``32FC1`` in metres) or ``sensor_msgs/CompressedImage`` (JPEG/PNG colour; ``compressedDepth``
PNG or a 16-bit PNG for depth); intrinsics from ``sensor_msgs/CameraInfo``.

Topics are found automatically when that is unambiguous: one colour image topic, one depth
topic (of several, the single one with ``aligned`` in its name: depth already registered to
colour), and the CameraInfo topic beside the colour topic. Otherwise ``dataset.rgb_topic``,
``dataset.depth_topic`` and ``dataset.camera_info_topic`` choose, and the error lists the
candidates. Colour and depth are paired by their header stamps exactly like the folder reader
pairs ``rgb.txt`` and ``depth.txt`` (``dataset.max_difference``, ``dataset.offset``).

Depth that is not registered to colour (a RealSense recording's raw depth stream, whose
CameraInfo differs from the colour one) is re-projected into the colour camera with the
recording's own depth-to-colour extrinsic, or with ``depth_camera``/``depth_to_color`` of a
camera file. Frames are decoded one at a time while the bag is read in order.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rgbdslam.datasets.registry import reader
from rgbdslam.datasets.base import Frame, Sequence
from rgbdslam.datasets.camera_file import CameraSetup, resolve_camera
from rgbdslam.datasets.tum import select_frames
from rgbdslam.io import validate
from rgbdslam.errors import InputError, cut, shorten
from rgbdslam.geometry.camera import Camera
from rgbdslam.geometry.depth_registration import DepthRegistration
from rgbdslam.io.trajectory import Trajectory, read_tum

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
COLOR_ENCODINGS = {"rgb8", "bgr8", "rgba8", "bgra8", "mono8", "8uc3", "8uc1"}
DEPTH_ENCODINGS = {"16uc1", "mono16", "32fc1"}
MM_PER_M = 1000.0


def bag_path(path: Path) -> Path | None:
    """The path to open for ``path`` (a ROS 1 file, a ROS 2 folder, or the lone ``.db3`` file
    that RealSense SDK 2.57+ records), or None."""
    path = Path(path)
    if path.is_file() and path.suffix == ".bag":
        return path
    if path.is_dir() and (path / "metadata.yaml").is_file():
        return path
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    if path.is_file() and path.suffix == ".db3":
        return path  # read with _SqliteBag
    return None


def _is_bag(path: Path) -> bool:
    return bag_path(path) is not None or (Path(path).is_file() and Path(path).suffix == ".mcap")


class _Conn:
    def __init__(self, cid: int, topic: str, msgtype: str):
        self.id, self.topic, self.msgtype = cid, topic, msgtype


class _SqliteBag:
    """A ROS 2 sqlite3 bag without metadata.yaml (what RealSense SDK 2.57+ records: one .db3
    file), read through the same calls as ``rosbags``' AnyReader; CDR messages are decoded with
    rosbags' ROS 2 Humble types."""

    def __init__(self, path: Path):
        import sqlite3

        from rosbags.typesys import Stores, get_typestore

        self.typestore = get_typestore(Stores.ROS2_HUMBLE)
        try:
            self.db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, check_same_thread=False)
            rows = self.db.execute("SELECT id, name, type FROM topics").fetchall()
        except sqlite3.DatabaseError as e:
            raise InputError(f"{path} cannot be read as a ROS 2 bag ({e}); check that the recording is complete") from None
        unknown = sorted({t for _, _, t in rows if t not in self.typestore.fielddefs})
        self.connections = [_Conn(i, n, t) for i, n, t in rows if t not in unknown]

    def messages(self, connections):
        by_id = {c.id: c for c in connections}
        if not by_id:
            return
        q = (f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN "
             f"({','.join(str(i) for i in by_id)}) ORDER BY timestamp, id")
        for tid, t, data in self.db.execute(q):
            yield by_id[tid], t, data

    def deserialize(self, raw, msgtype):
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self):
        self.db.close()


def _open_reader(path: Path):
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    where = bag_path(path)
    if where is None:  # a lone .mcap
        raise InputError(f"{path}: a ROS 2 bag is read from its folder with metadata.yaml; give the folder that "
                         f"holds {path.name} and metadata.yaml")
    if where.is_file() and where.suffix == ".db3":
        return _SqliteBag(where)
    try:
        reader = AnyReader([where], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, OSError, KeyError, ValueError) as e:
        raise InputError(f"{path} cannot be read as a ROS bag ({e}); check that the recording is complete") from None
    return reader


def decode_message(reader, raw, msgtype: str, topic: str, where) -> object:
    """The message ``raw`` of ``topic``; an InputError naming the topic and the bag when it cannot
    be decoded (a damaged or empty message: rosbags' SerdeError "Invalid or unsupported CDR
    encapsulation", a struct error for a truncated one)."""
    try:
        return reader.deserialize(raw, msgtype)
    except Exception as e:  # noqa: BLE001 - the third-party decoder's failure, whatever its class
        why = str(e).strip().splitlines()[0][:100] if str(e).strip() else "no detail"
        raise InputError(f"{where}: a message on {topic} cannot be decoded ({type(e).__name__}: {why}); the "
                         f"recording is damaged — record it again or leave that topic out") from None


def _stamp(msg, fallback_ns: int) -> float:
    header = getattr(msg, "header", None)
    st = getattr(header, "stamp", None)
    if st is not None:
        t = float(st.sec) + 1e-9 * float(st.nanosec)
        if t > 0:
            return t
    return 1e-9 * fallback_ns


def _kind(conn_msgtype: str, msg) -> tuple[str, str]:
    """('color' | 'depth' | 'unknown', encoding) of an image message."""
    if conn_msgtype == IMAGE:
        enc = msg.encoding.lower()
        if enc in COLOR_ENCODINGS:
            return "color", enc
        if enc in DEPTH_ENCODINGS:
            return "depth", enc
        return "unknown", msg.encoding
    fmt = msg.format.lower()
    if "compresseddepth" in fmt or fmt.startswith(("16uc1", "32fc1", "mono16")):
        return "depth", msg.format
    if any(k in fmt for k in ("jpeg", "jpg", "png", "rgb8", "bgr8")) or fmt == "":
        return "color", msg.format
    return "unknown", msg.format


def decode_color(msgtype: str, msg, topic: str) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an Image/CompressedImage colour message."""
    if msgtype == COMPRESSED:
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"{topic}: a compressed colour image cannot be decoded (format {shorten(msg.format)})")
        return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    enc = msg.encoding.lower()
    ch = {"rgb8": 3, "bgr8": 3, "8uc3": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8uc1": 1}.get(enc)
    if ch is None:
        raise InputError(f"{topic}: colour encoding {shorten(msg.encoding)} is not supported; use rgb8, bgr8, rgba8, "
                         f"bgra8 or mono8")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if data.size < h * step or step < w * ch:
        raise InputError(f"{topic}: image data holds {data.size} bytes, expected {h}x{step} for {w}x{h} {enc}")
    img = data[: h * step].reshape(h, step)[:, : w * ch].reshape(h, w, ch)
    code = {"bgr8": cv2.COLOR_BGR2RGB, "8uc3": cv2.COLOR_BGR2RGB, "rgba8": cv2.COLOR_RGBA2RGB,
            "bgra8": cv2.COLOR_BGRA2RGB, "mono8": cv2.COLOR_GRAY2RGB, "8uc1": cv2.COLOR_GRAY2RGB}.get(enc)
    return np.ascontiguousarray(img) if code is None else cv2.cvtColor(img, code)


def decode_depth(msgtype: str, msg, topic: str, metres_per_unit: float) -> np.ndarray:
    """(H, W) float32 metres of an Image/CompressedImage depth message (0 = no measurement).
    16-bit depth is scaled by ``metres_per_unit``; 32-bit float depth is in metres."""
    if msgtype == COMPRESSED:
        raw = bytes(msg.data)
        start = raw.find(b"\x89PNG")  # compressedDepth puts a 12-byte header before the PNG
        img = cv2.imdecode(np.frombuffer(raw[max(start, 0):], np.uint8), cv2.IMREAD_UNCHANGED) if start >= 0 else None
        if img is None or img.ndim != 2 or img.dtype != np.uint16:
            raise InputError(f"{topic}: compressed depth {shorten(msg.format)} is not a 16-bit PNG; record depth as "
                             f"16UC1 (compressedDepth png) or raw sensor_msgs/Image")
        if msg.format.lower().startswith("32fc1"):  # inverse-depth quantisation of compressed_depth_image_transport
            a, b = np.frombuffer(raw[4:12], "<f4")
            out = np.zeros(img.shape, np.float32)
            ok = img > 0
            out[ok] = a / (img[ok].astype(np.float32) - b)
            return out
        return img.astype(np.float32) * np.float32(metres_per_unit)
    enc = msg.encoding.lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if enc in ("16uc1", "mono16"):
        dt, size = np.dtype(">u2" if msg.is_bigendian else "<u2"), 2
    elif enc == "32fc1":
        dt, size = np.dtype(">f4" if msg.is_bigendian else "<f4"), 4
    else:
        raise InputError(f"{topic}: depth encoding {shorten(msg.encoding)} is not supported; use 16UC1 (mm) or 32FC1 (m)")
    data = np.frombuffer(bytes(msg.data), np.uint8)
    if data.size < h * step or step < w * size:
        raise InputError(f"{topic}: image data holds {data.size} bytes, expected {h}x{step} for {w}x{h} {enc}")
    img = data[: h * step].reshape(h, step)[:, : w * size].copy().view(dt).reshape(h, w)
    if enc == "32fc1":
        out = img.astype(np.float32)
        out[~np.isfinite(out) | (out < 0)] = 0.0
        return out
    return img.astype(np.float32) * np.float32(metres_per_unit)


def camera_from_info(msg, name: str) -> Camera:
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, dtype=np.float64)
    D = [float(x) for x in (getattr(msg, "d", None) if hasattr(msg, "d") else msg.D)]
    model = (msg.distortion_model or "plumb_bob").lower()
    if model not in ("plumb_bob", "rational_polynomial", "brown_conrady", "inverse_brown_conrady", "none", ""):
        raise InputError(f"{name}: distortion model {shorten(msg.distortion_model)} is not supported (plumb_bob, "
                         f"rational_polynomial); pass --camera FILE with undistorted intrinsics")
    # RealSense's "inverse" Brown-Conrady maps the other way than OpenCV's model; its coefficients
    # are small on the SDK's rectified colour stream, so it is read as no distortion (like `live`)
    if not any(D) or len(D) not in (4, 5, 8) or model == "inverse_brown_conrady":
        D = [0.0] * 5
    if K.size != 9 or not (K[0] > 0 and K[4] > 0):
        raise InputError(f"{name}: CameraInfo has no valid camera matrix K; pass --camera FILE")
    return validate.camera(float(K[0]), float(K[4]), float(K[2]), float(K[5]), int(msg.width), int(msg.height),
                           D, "camera_info", where=f"{name} (CameraInfo)")


def _transform(msg) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    q, t = msg.rotation, msg.translation
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    T[:3, 3] = [t.x, t.y, t.z]
    return T


@dataclass
class _Stream:
    topic: str
    msgtype: str
    encoding: str
    stamps: np.ndarray  # header stamps (s), one per message in bag order
    size: tuple[int, int]  # width, height of the first message


class RosbagSequence(Sequence):
    """Colour + depth from a ROS bag; see the module docstring."""

    def __init__(self, path: str | Path, cfg=None) -> None:
        from rgbdslam.datasets.config import DatasetConfig
        from rgbdslam.evaluation.associate import associate

        cfg = cfg or DatasetConfig()
        self.root = Path(path)
        self.name = self.root.stem if self.root.is_file() else self.root.resolve().name
        self._cfg = cfg
        reader = _open_reader(self.root)
        try:
            self._index(reader, cfg)
        finally:
            reader.close()
        ia, ib = associate(self.color.stamps, self.depth.stamps, cfg.max_difference, cfg.offset)
        if len(ia) == 0:
            raise InputError(f"no colour/depth pair in {self.root} has stamps within {cfg.max_difference} s "
                             f"(offset {cfg.offset} s); raise dataset.max_difference or check the topics "
                             f"{self.color.topic} and {self.depth.topic}")
        keep = select_frames(len(ia), cfg, self.root)
        self._ci, self._di = ia[keep], ib[keep]
        self._timestamps = self.color.stamps[self._ci]
        self.depth_timestamps = self.depth.stamps[self._di]
        self._iter = None
        self._next = 0
        self._pending: dict[tuple[str, int], tuple[str, object]] = {}

    # ------------------------------------------------------------------ indexing

    def _index(self, reader, cfg) -> None:
        conns = reader.connections
        images = [c for c in conns if c.msgtype in (IMAGE, COMPRESSED)]
        if not images:
            raise InputError(f"{self.root} has no sensor_msgs/Image or CompressedImage topic; "
                             f"topics: {', '.join(sorted({c.topic for c in conns})) or 'none'}")
        by_topic: dict[str, list] = {}
        for c in images:
            by_topic.setdefault(c.topic, []).append(c)
        # one pass over the image topics: stamps, kind and size (deserialising is a copy; no decoding)
        info: dict[str, dict] = {t: {"stamps": [], "kind": None, "enc": "", "size": None, "msgtype": cs[0].msgtype}
                                 for t, cs in by_topic.items()}
        for conn, t_ns, raw in reader.messages(connections=images):
            d = info[conn.topic]
            msg = decode_message(reader, raw, conn.msgtype, conn.topic, self.root)
            if d["kind"] is None:
                d["kind"], d["enc"] = _kind(conn.msgtype, msg)
                if conn.msgtype == IMAGE:
                    d["size"] = (int(msg.width), int(msg.height))
            d["stamps"].append(_stamp(msg, t_ns))
        colors = sorted(t for t, d in info.items() if d["kind"] == "color")
        depths = sorted(t for t, d in info.items() if d["kind"] == "depth")
        unknown = {t: d["enc"] for t, d in info.items() if d["kind"] == "unknown"}
        self.color = self._stream(info, self._pick(cfg.rgb_topic, colors, "colour", "rgb_topic", unknown, info), "colour")
        self.depth = self._stream(info, self._pick(cfg.depth_topic, depths, "depth", "depth_topic", unknown, info), "depth")
        infos = {c.topic: c for c in conns if c.msgtype == CAMERA_INFO}
        color_info = self._info_topic(cfg.camera_info_topic, infos, self.color.topic)
        depth_info = self._info_topic(None, infos, self.depth.topic, required=False)
        wanted = [infos[t] for t in {color_info, depth_info} if t is not None]
        first_info: dict[str, object] = {}
        for conn, _, raw in reader.messages(connections=wanted):
            first_info.setdefault(conn.topic, decode_message(reader, raw, conn.msgtype, conn.topic, self.root))
        realsense = self.depth.topic.startswith("/device_0/")
        if realsense:
            for stream in (self.color, self.depth):
                self._realsense_stamps(reader, conns, stream)
        own = None
        if color_info in first_info:
            own = CameraSetup(camera_from_info(first_info[color_info], color_info), f"CameraInfo on {color_info}")
        setup = resolve_camera(cfg, None, own)
        # depth units: 32FC1 is metres; 16-bit: dataset.depth_scale, the camera file's, a RealSense
        # recording's "Depth Units" option, else millimetres (the ROS convention)
        self.metres_per_unit = 1.0 / MM_PER_M
        units = self._realsense_units(reader, conns) if realsense else None
        if cfg.depth_scale is not None:
            self.metres_per_unit = 1.0 / cfg.depth_scale
        elif setup.depth_scale is not None:
            self.metres_per_unit = 1.0 / setup.depth_scale
        elif units is not None:
            self.metres_per_unit = units
        self.metres_per_unit *= cfg.depth_correction
        # depth not registered to colour: the camera file's extrinsic, else the recording's own
        if setup is own and depth_info in first_info and color_info in first_info:
            dcam = camera_from_info(first_info[depth_info], depth_info)
            ccam = setup.camera
            same = (dcam.fx, dcam.fy, dcam.cx, dcam.cy, dcam.width, dcam.height) == \
                (ccam.fx, ccam.fy, ccam.cx, ccam.cy, ccam.width, ccam.height)
            T = self._realsense_extrinsic(reader, conns) if realsense else None
            if not same or (T is not None and not np.allclose(T, np.eye(4), atol=1e-9)):
                if T is None:
                    raise InputError(
                        f"depth on {self.depth.topic} is not registered to colour (its CameraInfo {depth_info} differs "
                        f"from {color_info}) and the bag holds no extrinsic; record aligned depth, or pass --camera "
                        f"FILE with depth_camera and depth_to_color")
                setup = CameraSetup(setup.camera, setup.source, setup.depth_scale, dcam, T)
        self.camera_setup, self.camera = setup, setup.camera
        self.registration = (DepthRegistration(setup.depth_camera, setup.camera, setup.depth_to_color)
                             if setup.depth_camera is not None else None)
        for stream, cam, what in ((self.color, setup.camera, "colour"),
                                  (self.depth, setup.depth_camera or setup.camera, "depth")):
            if stream.size is not None and stream.size != (cam.width, cam.height):
                raise InputError(
                    f"{what} images on {stream.topic} are {stream.size[0]}x{stream.size[1]} but the camera "
                    f"({setup.source}) is {cam.width}x{cam.height}; pass --camera FILE with the intrinsics of "
                    f"these images")

    def _pick(self, chosen, found, what, key, unknown, info) -> str:
        if chosen:
            if chosen not in info:
                raise InputError(f"dataset.{key} '{chosen}' is not an image topic of {self.root}; image topics: "
                                 f"{', '.join(sorted(info))}")
            if info[chosen]["kind"] == "unknown":
                raise InputError(f"{chosen}: encoding {shorten(info[chosen]['enc'])} is not supported")
            kind = "color" if what == "colour" else "depth"
            if info[chosen]["kind"] != kind:  # checked here, not as every frame fails to decode
                other = "depth" if kind == "color" else "colour"
                raise InputError(f"dataset.{key} '{cut(chosen)}' is a {other} topic (encoding "
                                 f"{shorten(info[chosen]['enc'])}), not {what}; {what} topics of {self.root}: "
                                 f"{', '.join(found) or 'none'}")
            return chosen
        if len(found) == 1:
            return found[0]
        if not found:
            extra = (f"; unsupported encodings: " + ", ".join(f"{cut(t)} ({shorten(e)})" for t, e in sorted(unknown.items())[:5])
                     if unknown else "")
            raise InputError(f"{self.root} has no {what} image topic{extra}; {what} needs "
                             + ("16UC1/mono16 (mm) or 32FC1 (m) depth" if what == "depth" else
                                "rgb8/bgr8/rgba8/bgra8/mono8 or JPEG/PNG colour"))
        if what == "depth":
            aligned = [t for t in found if "aligned" in t]
            if len(aligned) == 1:
                return aligned[0]
        raise InputError(f"{self.root} has {len(found)} {what} image topics ({', '.join(found)}); choose one with "
                         f"--set dataset.{key}=TOPIC")

    @staticmethod
    def _stream(info, topic, what) -> _Stream:
        d = info[topic]
        return _Stream(topic, d["msgtype"], d["enc"], np.asarray(d["stamps"], dtype=np.float64), d["size"])

    def _info_topic(self, chosen, infos, image_topic, required=True) -> str | None:
        if chosen:
            if chosen not in infos:
                raise InputError(f"dataset.camera_info_topic '{chosen}' is not a CameraInfo topic of {self.root}; "
                                 f"CameraInfo topics: {', '.join(sorted(infos)) or 'none'}")
            return chosen
        if not infos:
            return None

        def common(a: str, b: str) -> int:
            pa, pb = a.strip("/").split("/"), b.strip("/").split("/")
            n = 0
            while n < min(len(pa), len(pb)) and pa[n] == pb[n]:
                n += 1
            return n

        scores = {t: common(t, image_topic) for t in infos}
        best = max(scores.values())
        winners = [t for t, s in scores.items() if s == best]
        if best == 0 or len(winners) > 1:
            if len(infos) == 1 and required:
                return next(iter(infos))
            if required and len(winners) > 1:
                raise InputError(f"several CameraInfo topics could belong to {image_topic} ({', '.join(sorted(winners))}); "
                                 f"choose one with --set dataset.camera_info_topic=TOPIC")
            return None
        return winners[0]

    def _realsense_units(self, reader, conns) -> float | None:
        """The 'Depth Units' option (metres per unit): Float32 (ROS 1 layout) or text (SDK 2.57+)."""
        topics = [c for c in conns if c.topic.startswith("/device_0/")
                  and c.topic.endswith(("Depth Units/value", "Depth_Units/value"))]
        for conn, _, raw in reader.messages(connections=topics):
            try:
                v = float(decode_message(reader, raw, conn.msgtype, conn.topic, self.root).data)
            except (TypeError, ValueError):
                continue
            if v > 0:
                return v
        return None

    def _realsense_extrinsic(self, reader, conns) -> np.ndarray | None:
        """Depth-to-colour extrinsic of a RealSense recording. Each stream's ``tf/...`` topic holds
        the extrinsic from the device's reference stream to that stream (SDK 2.57+: text
        'rotation=<9, column-major>;translation=<3>'; the ROS 1 layout: geometry_msgs/Transform),
        so depth-to-colour = T_ref_colour @ inv(T_ref_depth)."""
        def stream_tf(image_topic: str):
            base = image_topic.rsplit("/image/", 1)[0] + "/tf/"
            cs = [c for c in conns if c.topic.startswith(base)]
            for conn, _, raw in reader.messages(connections=cs):
                msg = decode_message(reader, raw, conn.msgtype, conn.topic, self.root)
                if hasattr(msg, "rotation"):
                    return _transform(msg)
                fields = dict(kv.split("=", 1) for kv in str(msg.data).split(";") if "=" in kv)
                try:
                    rot = np.array([float(x) for x in fields["rotation"].split(",")]).reshape(3, 3).T
                    T = np.eye(4)
                    T[:3, :3], T[:3, 3] = rot, [float(x) for x in fields["translation"].split(",")]
                except (KeyError, ValueError):
                    return None
                return T
            return None

        Tc, Td = stream_tf(self.color.topic), stream_tf(self.depth.topic)
        if Tc is None or Td is None or abs(np.linalg.det(Tc[:3, :3]) - 1) > 1e-3 or abs(np.linalg.det(Td[:3, :3]) - 1) > 1e-3:
            return None
        return Tc @ np.linalg.inv(Td)

    def _realsense_stamps(self, reader, conns, stream: _Stream) -> None:
        """SDK 2.57+ recordings stamp messages with the time since the recording started; the
        frame's own time stamp (ms) is in the stream's image/metadata text: use it."""
        base = stream.topic.rsplit("/image/", 1)[0] + "/image/metadata"
        cs = [c for c in conns if c.topic == base]
        stamps = []
        for conn, _, raw in reader.messages(connections=cs):
            text = str(decode_message(reader, raw, conn.msgtype, conn.topic, self.root).data)
            fields = dict(kv.split("=", 1) for kv in text.split(";") if "=" in kv)
            try:
                stamps.append(float(fields["timestamp"]) / 1000.0)
            except (KeyError, ValueError):
                return
        if len(stamps) == len(stream.stamps):
            stream.stamps = np.asarray(stamps, dtype=np.float64)

    # ------------------------------------------------------------------ frames

    @property
    def timestamps(self) -> np.ndarray:
        return self._timestamps

    def _messages(self):
        """(topic, ordinal, msgtype, raw) of the colour and depth messages, in bag order."""
        reader = _open_reader(self.root)
        try:
            conns = [c for c in reader.connections if c.topic in (self.color.topic, self.depth.topic)]
            count = {self.color.topic: 0, self.depth.topic: 0}
            for conn, _, raw in reader.messages(connections=conns):
                k = count[conn.topic]
                count[conn.topic] += 1
                yield conn.topic, k, conn.msgtype, raw, reader
        finally:
            reader.close()

    def _fetch(self, topic: str, k: int):
        key = (topic, k)
        while key not in self._pending:
            try:
                t, n, msgtype, raw, reader = next(self._iter)
            except StopIteration:
                raise InputError(f"{self.root}: message {k} of {topic} is missing (the bag changed while read?)") from None
            if (t == self.color.topic and n in self._want_c) or (t == self.depth.topic and n in self._want_d):
                self._pending[(t, n)] = (msgtype, decode_message(reader, raw, msgtype, t, self.root))
        return self._pending.pop(key)

    def load(self, i: int) -> Frame:
        if self._iter is None or i < self._next:  # (re)start reading from the bag's beginning
            if self._iter is not None:
                self._iter.close()
            self._iter = self._messages()
            self._pending = {}
            self._want_c, self._want_d = set(self._ci[i:].tolist()), set(self._di[i:].tolist())
        self._next = i + 1
        ci, di = int(self._ci[i]), int(self._di[i])
        mt_c, mc = self._fetch(self.color.topic, ci)
        mt_d, md = self._fetch(self.depth.topic, di)
        self._want_c.discard(ci)
        if di not in self._di[i + 1:]:
            self._want_d.discard(di)
        else:  # the same depth image pairs with a later colour image too: keep it
            self._pending[(self.depth.topic, di)] = (mt_d, md)
        rgb = decode_color(mt_c, mc, self.color.topic)
        depth = decode_depth(mt_d, md, self.depth.topic, self.metres_per_unit)
        cam = self.camera
        dcam = self.camera_setup.depth_camera or cam
        if rgb.shape[:2] != (cam.height, cam.width) or depth.shape != (dcam.height, dcam.width):
            raise InputError(f"{self.root}: frame {i} is {rgb.shape[1]}x{rgb.shape[0]} colour / "
                             f"{depth.shape[1]}x{depth.shape[0]} depth but the camera is {cam.width}x{cam.height}; "
                             f"pass --camera FILE matching the images")
        if self.registration is not None:
            depth = self.registration(depth)
        return Frame(i, float(self._timestamps[i]), rgb, depth, cam, f"{self.color.topic}#{ci}",
                     depth_delay=float(self.depth_timestamps[i] + self._cfg.offset - self._timestamps[i]))

    def groundtruth(self) -> Trajectory | None:
        """A TUM trajectory given by ``dataset.groundtruth`` (bags rarely carry one)."""
        p = getattr(self._cfg, "groundtruth", None)
        return read_tum(Path(p)) if p else None


reader("rosbag", _is_bag)(RosbagSequence)
