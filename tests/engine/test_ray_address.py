"""A Ray address that cannot work is one line within seconds, before Ray is asked (Ray waits a
minute printing its C++ log lines for a closed port or an unknown host, and raises tracebacks for
an empty, ``http://`` or — without ``ray[client]`` — ``ray://`` address)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

import pytest

from tests.conftest import REPO


def _closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    return port


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    from rgbdslam.datasets.synthetic import generate_sequence

    out = tmp_path_factory.mktemp("ray_address") / "syn"
    generate_sequence(out, frames=3, motion="loop", seed=0)
    return out


CLOSED = _closed_port()


@pytest.mark.parametrize("address, words", [
    (f"127.0.0.1:{CLOSED}", f"no Ray cluster at 127.0.0.1:{CLOSED} (connection refused within 3 s)"),
    (f"ray://127.0.0.1:{CLOSED}", f"no Ray cluster at ray://127.0.0.1:{CLOSED} (connection refused"),
    ("nosuchhost.invalid:6379", "the host nosuchhost.invalid is unknown"),
    ("", "--address '' is not a Ray cluster address; give auto, HOST:6379 or ray://HOST:10001"),
    ("http://127.0.0.1:8265", "--address 'http://127.0.0.1:8265' is not a Ray cluster address"),
    ("127.0.0.1", "--address '127.0.0.1' has no HOST:PORT"),
])
def test_a_bad_ray_address_is_one_line_within_seconds(sequence, tmp_path, address, words):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    start = time.monotonic()
    res = subprocess.run([sys.executable, "-m", "rgbdslam._entry", "sweep", str(sequence), "--grid",
                          "features.n_features=500", "--engine", "ray", "--address", address, "--out",
                          str(tmp_path / "sweep"), "-q"], env=env, capture_output=True, text=True, timeout=60)
    took = time.monotonic() - start
    assert res.returncode == 2, res.stderr[-2000:]
    assert res.stderr.count("\n") == 1 and res.stderr.startswith("error: ") and words in res.stderr, res.stderr
    assert took < 15, took
