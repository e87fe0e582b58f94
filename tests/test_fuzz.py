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

from rgbdslam.errors import RgbdslamError

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
