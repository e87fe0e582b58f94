"""Signals end a command cleanly, with real processes and real signals: SIGTERM (kill, timeout,
a batch scheduler, docker stop) is handled as Ctrl-C — run.json says "interrupted", no map/.fusing-*
folder is left, exit 143 with one line —; every helper process ends with its run, also when the
run is killed with SIGKILL; a Ctrl-C while the helpers start prints no helper traceback."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import REPO


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    from rgbdslam.datasets.synthetic import generate_sequence

    out = tmp_path_factory.mktemp("signals") / "syn"
    generate_sequence(out, frames=150, motion="loop", seed=3)
    return out


def _start(sequence: Path, out: Path) -> subprocess.Popen:
    """``rgbdslam run`` with the live map (helper processes), in a session of its own (a terminal's
    process group: a Ctrl-C reaches every process in it)."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-m", "rgbdslam._entry", "run", str(sequence), "--out", str(out)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)


def _children(pid: int) -> set[int]:
    kids = set()
    for p in Path("/proc").iterdir():
        if p.name.isdigit():
            try:
                fields = (p / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                kids.add(int(p.name))
    return kids


def _alive(pids: set[int]) -> set[int]:
    out = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            out.add(pid)
    return out


def _wait_for(condition, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.05)
    return condition()


def _helpers_running(proc: subprocess.Popen, out: Path, count: int = 3) -> set[int]:
    """The run's child processes once it is tracking with ``count`` of them (tracker + map + cloud)."""
    assert _wait_for(lambda: len(_children(proc.pid)) >= count and (out / "run.json").is_file(), 60), \
        proc.stderr.read() if proc.poll() is not None else "no helpers"
    return _children(proc.pid)


@pytest.mark.parametrize("to", ["run", "group"])
def test_sigterm_is_handled_like_ctrl_c(sequence, tmp_path, to):
    """SIGTERM to the run (kill, timeout, docker stop) or to its whole process group (systemd, a
    batch scheduler): the helpers neither die under the run nor outlive it."""
    out = tmp_path / "run"
    proc = _start(sequence, out)
    kids = _helpers_running(proc, out)
    try:
        assert json.loads((out / "run.json").read_text())["status"] == "running"
        if to == "run":
            proc.send_signal(signal.SIGTERM)
        else:
            os.killpg(proc.pid, signal.SIGTERM)
        assert _wait_for(lambda: proc.poll() is not None, 60)
        assert proc.returncode == 143
        assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
        assert not list(out.rglob(".fusing-*"))
        assert _wait_for(lambda: not _alive(kids), 10), _alive(kids)
        _, err = proc.communicate(timeout=10)
        assert err.splitlines()[-1] == "terminated (SIGTERM): finished work was saved" and "Traceback" not in err, err
        assert "ended unexpectedly" not in err, err
    finally:
        _kill(proc, kids)


def test_helpers_end_with_a_killed_run(sequence, tmp_path):
    out = tmp_path / "run"
    proc = _start(sequence, out)
    kids = _helpers_running(proc, out)
    try:
        proc.kill()  # SIGKILL: the run cannot clean up; its helpers must notice on their own
        assert _wait_for(lambda: not _alive(kids), 10), _alive(kids)
    finally:
        _kill(proc, kids)


@pytest.mark.parametrize("after", [0.0, 0.5, 1.0, 1.5, 2.0])
def test_ctrl_c_while_the_helpers_start_prints_no_traceback(sequence, tmp_path, after):
    """Ctrl-C ``after`` s from the first helper's start: helpers importing, being launched, taking
    their first jobs."""
    out = tmp_path / "run"
    proc = _start(sequence, out)
    kids: set[int] = set()
    try:
        assert _wait_for(lambda: len(_children(proc.pid)) >= 2, 60)  # the resource tracker and a helper
        time.sleep(after)
        kids = _children(proc.pid)
        os.killpg(proc.pid, signal.SIGINT)  # what the terminal does on Ctrl-C: the whole process group
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == 130, err
        assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
        assert err.splitlines()[-1] == "interrupted: finished work was saved", err
        assert _wait_for(lambda: not _alive(kids), 10), _alive(kids)
    finally:
        _kill(proc, kids)


def _kill(proc: subprocess.Popen, kids: set[int]) -> None:
    """Leave no process behind when a test fails (the code before these fixes orphaned them)."""
    for pid in _alive(kids | _children(proc.pid)):
        os.kill(pid, signal.SIGKILL)
    if proc.poll() is None:
        proc.kill()
    proc.communicate()
