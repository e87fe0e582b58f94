"""Property-based fuzzing of every text parser and of ``--set`` values (issue 16).

Arbitrary bytes and mutated valid files must end in a correct parse or one clean error line
(an RgbdslamError whose text has no newline), never another exception and never a hang (each
example runs under a 10 s alarm). The cost is bounded for CI: a fixed number of examples per
test (FUZZ_EXAMPLES, default 150), derandomized (the same examples on every run, no example
database), so the suite's time and verdict do not vary. RGBDSLAM_FUZZ_EXAMPLES raises it for a
longer local campaign.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rgbdslam.errors import MAX_MESSAGE, RgbdslamError

FUZZ_EXAMPLES = int(os.environ.get("RGBDSLAM_FUZZ_EXAMPLES", "150"))
FUZZ = settings(max_examples=FUZZ_EXAMPLES, derandomize=True, database=None, deadline=None,
                suppress_health_check=list(HealthCheck), print_blob=True)

# ------------------------------------------------------------------------------- valid samples

TUM = """# timestamp tx ty tz qx qy qz qw
1305031102.175304 1.3405 0.6266 1.6575 0.6574 0.6126 -0.2949 -0.3248
1305031102.211214 1.3303 0.6256 1.6464 0.6579 0.6161 -0.2932 -0.3189
1305031102.243211 1.3160 0.6254 1.6302 0.6609 0.6199 -0.2893 -0.3086
1305031102.275326 1.3035 0.6253 1.6168 0.6633 0.6224 -0.2864 -0.3000
"""
LIST = """# color images
# file: 'rgbd_dataset_freiburg1_desk.bag'
# timestamp filename
1305031102.175304 rgb/1305031102.175304.png
1305031102.211214 rgb/1305031102.211214.png
1305031102.243211 rgb/1305031102.243211.png
"""
ASSOC = """1305031102.175304 rgb/1305031102.175304.png 1305031102.160407 depth/1305031102.160407.png
1305031102.211214 rgb/1305031102.211214.png 1305031102.226738 depth/1305031102.226738.png
"""
CAMERA = """camera: fr1
fx: 517.3
fy: 516.5
cx: 318.6
cy: 255.3
width: 640
height: 480
dist: [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]
"""
CONFIG = """dataset:
  kind: tum
  camera: fr1
  max_difference: 0.02
features:
  n_features: 800
  grid_rows: 2
registration:
  method: islam
  guided_gate: null
loop:
  enabled: false
mapping: {voxel_size: 0.02, seed: 3}
"""
G2O_SE2 = """VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1.0 0.1 0.05
VERTEX_SE2 2 2.0 0.1 0.1
EDGE_SE2 0 1 1.0 0.1 0.05 100 0 0 100 0 400
EDGE_SE2 1 2 1.0 0.0 0.05 100 0 0 100 0 400
EDGE_SE2 0 2 2.0 0.1 0.1 100 0 0 100 0 400
FIX 0
"""
G2O_SE3 = """VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1
VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1
EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 100 0 0 0 0 0 100 0 0 0 0 100 0 0 0 400 0 0 400 0 400
"""
TORO = """VERTEX2 0 0 0 0
VERTEX2 1 1 0 0.1
EDGE2 0 1 1 0 0.1 100 0 100 400 0 0
"""
ISAM = """ODOMETRY 0 1 1.03039 0.0113498 -0.0129577 44.72135955 0 0 44.72135955 0 44.72135955
ODOMETRY 1 2 1.0139 -0.0586393 -0.013225 44.72135955 0 0 44.72135955 0 44.72135955
EDGE2 0 2 2.0 0 0 44.72135955 0 0 44.72135955 0 44.72135955
"""
RUN_JSON = json.dumps({"sequence": "/nonexistent/seq", "frames": 4, "tracked": 4, "keyframes": [0, 2],
                       "loops": [[0, 2]], "segments": [{"first": 0, "last": 3, "frames": 4, "map": True}],
                       "status": "finished", "interrupted": False}, indent=2)

# ------------------------------------------------------------------------------- the property


@contextlib.contextmanager
def _alarm(seconds: int = 10):
    def hang(*_):
        raise TimeoutError(f"no answer within {seconds} s: a hang")

    previous = signal.signal(signal.SIGALRM, hang)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def clean_parse_or_one_line_error(call, *args) -> None:
    """``call(*args)`` returns, or raises RgbdslamError with one non-empty line of text."""
    with _alarm():
        try:
            call(*args)
        except RgbdslamError as e:
            text = str(e)
            assert text.strip() and "\n" not in text and "\r" not in text, repr(text)
            assert len(text) <= MAX_MESSAGE, len(text)


# number-ish tokens that hit the checks: huge, tiny, non-finite, C-int edges, negative zero
TOKENS = ["0", "-0", "1", "-1", "1e300", "-1e300", "1e-300", "nan", "inf", "-inf", "2147483648",
          "9007199254740993", "1e16", "0x10", "1_000", "", " ", "\t", "#", ",", "\x00", "é", "\u2028", "---", ":",
          "[", "{", "}", "]", "null", "~", "'", '"', "&a", "*a", "!!python/object:os.system", "<<: *a"]


@st.composite
def mutated(draw, text: str):
    """``text`` after a few random edits: a token replaced by one of TOKENS or random text,
    characters deleted or inserted, lines duplicated, dropped or swapped, the end cut off."""
    lines = text.split("\n")
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["token", "delete", "insert", "dup", "drop", "swap", "cut"]))
        k = draw(st.integers(0, max(len(lines) - 1, 0)))
        if not lines:
            lines = [""]
            k = 0
        if op == "token":
            parts = lines[k].split(" ")
            i = draw(st.integers(0, len(parts) - 1))
            parts[i] = draw(st.one_of(st.sampled_from(TOKENS), st.text(max_size=12),
                                      st.floats().map(repr), st.integers().map(str)))
            lines[k] = " ".join(parts)
        elif op in ("delete", "insert"):
            s = lines[k]
            i = draw(st.integers(0, len(s)))
            lines[k] = s[:i] + (draw(st.text(max_size=4)) if op == "insert" else "") + s[i + 1:]
        elif op == "dup":
            lines.insert(k, lines[k])
        elif op == "drop" and len(lines) > 1:
            lines.pop(k)
        elif op == "swap":
            j = draw(st.integers(0, len(lines) - 1))
            lines[k], lines[j] = lines[j], lines[k]
        elif op == "cut":
            whole = "\n".join(lines)
            lines = whole[: draw(st.integers(0, len(whole)))].split("\n")
    return "\n".join(lines)


def file_contents(sample: str):
    """Arbitrary bytes, arbitrary text, or a mutated valid file (as UTF-8 bytes)."""
    return st.one_of(st.binary(max_size=300), st.text(max_size=300).map(lambda s: s.encode("utf-8", "surrogatepass")),
                     mutated(sample).map(lambda s: s.encode("utf-8", "surrogatepass")))


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    p = tmp_path / name
    p.write_bytes(data)
    return p


# ------------------------------------------------------------------------------- the parsers


@FUZZ
@given(data=file_contents(TUM))
def test_fuzz_tum_trajectory(tmp_path_factory, data):
    from rgbdslam.io.trajectory import read_tum

    clean_parse_or_one_line_error(read_tum, _write(tmp_path_factory.mktemp("t"), "traj.tum", data))


@FUZZ
@given(data=file_contents(LIST), assoc=file_contents(ASSOC))
def test_fuzz_tum_lists(tmp_path_factory, data, assoc):
    from rgbdslam.datasets.tum import read_associations, read_file_list

    d = tmp_path_factory.mktemp("l")
    clean_parse_or_one_line_error(read_file_list, _write(d, "rgb.txt", data))
    clean_parse_or_one_line_error(read_associations, _write(d, "assoc.txt", assoc))


@FUZZ
@given(data=file_contents(CAMERA))
def test_fuzz_camera_yaml(tmp_path_factory, data):
    from rgbdslam.datasets.tum import camera_from_yaml

    clean_parse_or_one_line_error(camera_from_yaml, _write(tmp_path_factory.mktemp("c"), "camera.yaml", data))


@FUZZ
@given(data=file_contents(CONFIG))
def test_fuzz_config_yaml(tmp_path_factory, data):
    from rgbdslam.config import load_config

    clean_parse_or_one_line_error(load_config, _write(tmp_path_factory.mktemp("y"), "cfg.yaml", data))


@FUZZ
@given(data=st.one_of(file_contents(G2O_SE2), file_contents(G2O_SE3)),
       fmt=st.sampled_from(["auto", "g2o"]))
def test_fuzz_g2o_graphs(tmp_path_factory, data, fmt):
    from rgbdslam.posegraph.graph_io import read_graph

    clean_parse_or_one_line_error(read_graph, _write(tmp_path_factory.mktemp("g"), "graph.g2o", data), fmt)


@FUZZ
@given(data=st.one_of(file_contents(TORO), file_contents(ISAM)), fmt=st.sampled_from(["auto", "toro", "isam"]))
def test_fuzz_toro_and_isam_graphs(tmp_path_factory, data, fmt):
    from rgbdslam.posegraph.graph_io import read_graph

    clean_parse_or_one_line_error(read_graph, _write(tmp_path_factory.mktemp("g"), "graph.txt", data), fmt)


@FUZZ
@given(data=file_contents(RUN_JSON))
def test_fuzz_run_json(tmp_path_factory, data):
    from rgbdslam.runfolder.read import read_run

    d = tmp_path_factory.mktemp("r")
    _write(d, "run.json", data)
    (d / "trajectory.tum").write_text(TUM)
    (d / "config.yaml").write_text("")
    clean_parse_or_one_line_error(read_run, d)


STEREO_YAML = """fx: 718.856
fy: 718.856
cx: 607.1928
cy: 185.2157
baseline: 0.5371
fps: 10
width: 1241
height: 376
"""
SENSOR_YAML = """%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
         0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
         -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [752, 480]
camera_model: pinhole
intrinsics: [458.654, 457.296, 367.215, 248.375]
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""
EUROC_CSV = """#timestamp [ns],filename
1403636579763555584,1403636579763555584.png
1403636579813555456,1403636579813555456.png
1403636579863555584,1403636579863555584.png
"""
EUROC_GT = """#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []
1403636580838555648,4.688319,-1.786938,0.783338,0.534108,-0.153029,-0.827383,-0.082152
1403636580843555328,4.688177,-1.786770,0.787350,0.534640,-0.152990,-0.826976,-0.082863
"""
KITTI_CALIB = """P0: 7.188560e+02 0.000000e+00 6.071928e+02 0.000000e+00 0.000000e+00 7.188560e+02 1.852157e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
P1: 7.188560e+02 0.000000e+00 6.071928e+02 -3.861448e+02 0.000000e+00 7.188560e+02 1.852157e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00
"""
KITTI_POSES = """1.000000e+00 9.043680e-12 2.326809e-11 5.551115e-17 9.043683e-12 1.000000e+00 2.392370e-10 3.330669e-16 2.326810e-11 2.392370e-10 9.999999e-01 -4.440892e-16
9.999978e-01 5.272628e-04 -2.066935e-03 -4.690294e-02 -5.296506e-04 9.999992e-01 -1.154865e-03 -2.839928e-02 2.066324e-03 1.155958e-03 9.999971e-01 8.586941e-01
"""
KITTI_TIMES = """0.000000e+00
1.036330e-01
2.072660e-01
"""
SEVEN_K = """585 0 320
0 585 240
0 0 1
"""
SEVEN_POSE = """9.9935108e-001 -3.2676521e-002 1.5571418e-002 -1.0055915e-001
3.1311993e-002 9.9643254e-001 7.8383312e-002 -3.4068734e-001
-1.8085200e-002 -7.7846035e-002 9.9680173e-001 2.0108354e-001
0.0000000e+000 0.0000000e+000 0.0000000e+000 1.0000000e+000
"""

# ------------------------------------------------------------------------------- the newer readers


@FUZZ
@given(data=file_contents(STEREO_YAML))
def test_fuzz_stereo_yaml(tmp_path_factory, data):
    from rgbdslam.datasets.stereo_folder import read_stereo_yaml

    clean_parse_or_one_line_error(read_stereo_yaml, _write(tmp_path_factory.mktemp("s"), "stereo.yaml", data))


@FUZZ
@given(sensor=file_contents(SENSOR_YAML), csv=file_contents(EUROC_CSV), gt=file_contents(EUROC_GT))
def test_fuzz_euroc_files(tmp_path_factory, sensor, csv, gt):
    from rgbdslam.datasets.euroc import read_camera_csv, read_groundtruth_csv, read_sensor_yaml

    d = tmp_path_factory.mktemp("e")

    def sensor_then_opencv(path):  # what the reader gives OpenCV must not crash it
        import cv2
        import numpy as np

        s = read_sensor_yaml(path)
        cv2.initUndistortRectifyMap(s["K"], s["dist"], np.eye(3), s["K"], s["size"], cv2.CV_32FC1)

    clean_parse_or_one_line_error(sensor_then_opencv, _write(d, "sensor.yaml", sensor))
    clean_parse_or_one_line_error(read_camera_csv, _write(d, "data.csv", csv))
    clean_parse_or_one_line_error(read_groundtruth_csv, _write(d, "gt.csv", gt))


@FUZZ
@given(calib=file_contents(KITTI_CALIB), poses=file_contents(KITTI_POSES), times=file_contents(KITTI_TIMES))
def test_fuzz_kitti_files(tmp_path_factory, calib, poses, times):
    from rgbdslam.io.kitti import read_kitti_calib, read_kitti_poses, read_kitti_times
    from rgbdslam.io.validate import camera

    d = tmp_path_factory.mktemp("k")

    def calib_camera(path):  # the reader's check of P0 (KittiSequence)
        P = read_kitti_calib(path).get("P0")
        if P is not None:
            camera(P[0, 0], P[1, 1], P[0, 2], P[1, 2], 1, 1, where=str(path))

    clean_parse_or_one_line_error(calib_camera, _write(d, "calib.txt", calib))
    clean_parse_or_one_line_error(read_kitti_poses, _write(d, "00.txt", poses))
    clean_parse_or_one_line_error(read_kitti_times, _write(d, "times.txt", times))


@FUZZ
@given(k=file_contents(SEVEN_K), pose=file_contents(SEVEN_POSE))
def test_fuzz_7scenes_files(tmp_path_factory, k, pose):
    from rgbdslam.datasets.sevenscenes import read_intrinsics, read_pose

    d = tmp_path_factory.mktemp("7")
    clean_parse_or_one_line_error(read_intrinsics, _write(d, "camera-intrinsics.txt", k))
    clean_parse_or_one_line_error(read_pose, _write(d, "frame-000000.pose.txt", pose))


NUMBERS = st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -1.0, 1e300, -1e300, 1e-300]),
                    st.integers(-2 ** 40, 2 ** 40))


@FUZZ
@given(k=st.lists(NUMBERS, min_size=0, max_size=12), d=st.lists(NUMBERS, max_size=9),
       width=st.integers(-2 ** 33, 2 ** 33), height=st.integers(-2 ** 33, 2 ** 33),
       model=st.sampled_from(["plumb_bob", "rational_polynomial", "equidistant", "", "x" * 5000]))
def test_fuzz_bag_camera_info(k, d, width, height, model):
    """A bag's CameraInfo with any K, D, size and model: a camera or one line (rosbags' own
    message class, as the reader gets it)."""
    import numpy as np
    from rosbags.typesys import Stores, get_typestore

    from rgbdslam.datasets.rosbag import camera_from_info

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    msg = T["sensor_msgs/msg/CameraInfo"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="c"),
        height=height % 2 ** 32, width=width % 2 ** 32, distortion_model=model, d=np.array(d, dtype=np.float64),
        k=np.array(k, dtype=np.float64), r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
    clean_parse_or_one_line_error(camera_from_info, msg, "/camera/color/camera_info")


@FUZZ
@given(raw=st.one_of(st.binary(max_size=200), st.binary(min_size=4, max_size=200).map(lambda b: b"\x00\x01\x00\x00" + b)),
       msgtype=st.sampled_from(["sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
                                "sensor_msgs/msg/CameraInfo"]))
def test_fuzz_bag_messages(raw, msgtype):
    """Any bytes as a ROS 2 message (empty, damaged, a valid header with garbage): a message or one
    line naming the topic (decode_message, what every read of a bag message goes through)."""
    from rosbags.typesys import Stores, get_typestore

    from rgbdslam.datasets.rosbag import decode_message

    class Reader:  # rosbags' decoder, as both bag readers call it
        typestore = get_typestore(Stores.ROS2_HUMBLE)

        def deserialize(self, data, kind):
            return self.typestore.deserialize_cdr(data, kind)

    clean_parse_or_one_line_error(decode_message, Reader(), raw, msgtype, "/camera/color/image_raw", "bag")


def _small_map(path: Path):
    """A valid two-keyframe map file (every array of the format, consistent shapes)."""
    import numpy as np

    from rgbdslam.geometry.camera import CAMERAS
    from rgbdslam.session.mapfile import ARRAYS, MapData, save_map

    sizes = {"K": 2, "K+1": 3, "N": 4, "F": 2, "E": 1, "L": 1}
    out = {}
    for name, (dtype, shape) in ARRAYS.items():
        dims = tuple(sizes.get(d, d) if isinstance(d, str) else d for d in shape)
        out[name] = np.zeros(dims, dtype=dtype)
    for name in ("kf_pose", "frame_rel", "odo_T", "loop_T"):
        out[name][:] = np.eye(4)
    for name in ("odo_info", "loop_info"):
        out[name][:] = np.eye(6)
    out["kf_feature_start"][:] = [0, 2, 4]
    out["odo_ij"][:] = [0, 1]
    out["loop_ij"][:] = [0, 1]
    out["frame_kf"][:] = [0, 1]
    out["kf_frame"][:] = [0, 1]
    out["frame_index"][:] = [0, 1]
    out["kf_timestamp"][:] = out["frame_timestamp"][:] = [0.0, 0.1]
    return save_map(path, MapData(out, CAMERAS["fr1"]))


@FUZZ
@given(name=st.sampled_from(["kf_pose", "frame_rel", "odo_T", "loop_T", "odo_info", "loop_info", "kf_timestamp",
                             "frame_timestamp", "odo_ij", "frame_kf", "kf_feature_start", "feat_uv"]),
       index=st.integers(0, 10 ** 6), value=NUMBERS, cut=st.one_of(st.none(), st.integers(0, 4000)),
       flip=st.one_of(st.none(), st.tuples(st.integers(0, 10 ** 6), st.integers(1, 255))))
def test_fuzz_map_file(tmp_path_factory, name, index, value, cut, flip):
    """A saved map with any value in any array (written with a valid checksum, as a crafted file
    would be), then cut short or with a byte changed: a map or one line."""
    import numpy as np

    from rgbdslam.session.mapfile import ARRAYS, checksum, load_map, read_header

    d = tmp_path_factory.mktemp("m")
    base = _small_map(d / "map.npz")
    with np.load(base) as z:
        arrays = {n: z[n].copy() for n in ARRAYS}
    a = arrays[name]
    flat = a.reshape(-1)
    if flat.size:
        with np.errstate(all="ignore"):
            try:
                flat[index % flat.size] = value
            except (OverflowError, ValueError):
                flat[index % flat.size] = 0
    header = read_header(base)
    header["sha256"] = checksum(arrays)  # a crafted file: its checksum matches
    path = d / "crafted.npz"
    np.savez(path, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **arrays)
    data = bytearray(path.read_bytes())
    if flip is not None:
        data[flip[0] % len(data)] ^= flip[1]
    if cut is not None:
        data = data[:cut]
    path.write_bytes(bytes(data))
    clean_parse_or_one_line_error(load_map, path)


def _config_keys() -> list[str]:
    import dataclasses

    from rgbdslam.config import Config

    cfg = Config()
    return [f"{s.name}.{f.name}" for s in dataclasses.fields(cfg) for f in dataclasses.fields(getattr(cfg, s.name))]


@FUZZ
@given(key=st.one_of(st.sampled_from(_config_keys()), st.text(max_size=20)),
       value=st.one_of(st.sampled_from(TOKENS), st.text(max_size=30), st.floats().map(repr),
                       st.integers().map(str), st.sampled_from(["[1, 2]", "{a: 1}", "true", "yes", "off", "1e9",
                                                                "2**31", "!!binary aGVsbG8=", "0o17", "1:30"])))
def test_fuzz_set_values(key, value):
    """--set SECTION.KEY=VALUE with any key and any text: a config or one error line."""
    from rgbdslam.config import load_config

    clean_parse_or_one_line_error(load_config, None, [f"{key}={value}"])


def test_fuzz_settings_are_bounded_and_deterministic():
    """The CI cost stays fixed: a bounded number of examples, derandomized, no example database."""
    assert FUZZ.derandomize and FUZZ.database is None
    if "RGBDSLAM_FUZZ_EXAMPLES" not in os.environ:
        assert FUZZ.max_examples == 150
