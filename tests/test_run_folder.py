"""The run folder's promises (issue 16): Ctrl-C at any moment (exit 130, run.json says
interrupted, no traceback), one run at a time (a lock), previous/ only ever holding and losing
what rgbdslam wrote (a manifest), a full disk (one line naming the file, run.json never claiming
success, earlier outputs intact) and the small path cases of the command line."""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from rgbdslam.cli import main

from tests.conftest import LIMITED_FSIZE

pytestmark = pytest.mark.data  # every test here runs on the shared TUM frames

QUICK = ["-q", "--set", "output.plots=false", "--set", "mapping.map2d=false"]


def _status(run: Path) -> dict:
    return json.loads((run / "run.json").read_text())


def _sigint_self(*_, **__):
    os.kill(os.getpid(), signal.SIGINT)  # a real Ctrl-C, delivered to this process
    time.sleep(1)


# ----------------------------------------------------------------------------- class 3: Ctrl-C


@pytest.mark.parametrize("target, stage, extra", [
    ("rgbdslam.pipeline.SLAM.__init__", "start-up", []),
    ("rgbdslam.pipeline.evaluate", "evaluation", []),
    ("rgbdslam.pipeline._map_summary", "map", []),  # waiting for the map fused while tracking
    ("rgbdslam.mapping.fusion.fuse_run", "map", ["--set", "mapping.live=false"]),  # fused after the run
])
def test_ctrl_c_at_any_stage_says_interrupted(desk9, tmp_path, monkeypatch, target, stage, extra):
    """Ctrl-C during start-up (the folder exists), evaluation or fusion: exit 130, one line,
    run.json "interrupted" naming the stage; a finished run already there moved to previous/."""
    run = tmp_path / "run"
    assert CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK, *extra]).exit_code == 0
    monkeypatch.setattr(target, _sigint_self)
    # Python's handler installed again at the C level: a library loaded by an earlier test of the same
    # process may have replaced it with its own (signal.getsignal still names Python's), and the console
    # script installs its own first thing anyway (rgbdslam/_entry.py)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK, *extra])
    assert res.exit_code == 130, res.output
    assert res.stderr.splitlines()[-1] == "interrupted: finished work was saved" and "Traceback" not in res.output
    s = _status(run)
    assert s["status"] == "interrupted" and s["interrupted"] is True and s["stopped_during"] == stage
    assert _status(run / "previous")["status"] == "finished"


@pytest.mark.parametrize("delay", [0.0, 1.5, 3.0])
def test_ctrl_c_in_a_real_process_is_never_a_traceback(desk9, tmp_path, delay):
    """The console script under a real SIGINT at several moments (imports, start-up, tracking):
    exit 130 with the one line, and run.json, when the folder exists, says interrupted. The child
    starts with SIGINT blocked, as under a shell that is still starting it: a Ctrl-C during the
    interpreter's own start-up (delay 0, or a slow machine) waits until the console script takes
    it, so the test does not depend on the machine's speed."""
    exe = Path(sys.executable).parent / "rgbdslam"
    run = tmp_path / "run"

    def block():
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})

    p = subprocess.Popen([str(exe), "run", str(desk9), "--out", str(run), *QUICK], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=block)
    time.sleep(delay)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    if p.returncode == 0:  # the machine was fast: the run had finished
        assert _status(run)["status"] == "finished"
        return
    assert p.returncode == 130 and "Traceback" not in err, err
    assert err.splitlines()[-1] == "interrupted: finished work was saved"
    if (run / "run.json").exists():
        assert _status(run)["status"] == "interrupted"


def test_a_ctrl_c_inside_the_import_machinery_is_raised_again_after_it():
    """The handler called from a frame of importlib's own code (compiled under its code name) does
    not raise there — a KeyboardInterrupt there can leave the global import lock held — but sends
    the signal again; raised anywhere else it is the KeyboardInterrupt, as before."""
    from rgbdslam import errors

    got = []
    old = signal.signal(signal.SIGINT, lambda s, f: got.append(s))
    try:
        was = errors._interrupted
        code = compile("errors.on_sigint(signal.SIGINT, sys._getframe())", "<frozen importlib._bootstrap>", "exec")
        exec(code, {"errors": errors, "signal": signal, "sys": sys})  # returns: nothing raised
        assert errors._interrupted == was  # not yet an interruption
        deadline = time.monotonic() + 5
        while not got and time.monotonic() < deadline:
            time.sleep(0.01)
        assert got == [signal.SIGINT]  # sent again, to whatever handler is in place then
        with pytest.raises(KeyboardInterrupt):
            errors.on_sigint(signal.SIGINT, sys._getframe())
        assert errors._interrupted
    finally:
        errors._interrupted = False
        signal.signal(signal.SIGINT, old)


# ----------------------------------------------------------------------------- class 4: lock

_HOLD = """
import sys, time
from rgbdslam.runfolder.folder import folder_lock
with folder_lock(sys.argv[1], "run"):
    print("locked", flush=True)
    time.sleep(600)
"""


def test_a_second_run_into_a_busy_folder_is_one_line_and_a_killed_holder_frees_it(desk9, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK])
        assert res.exit_code == 2 and res.stderr.count("\n") == 1, res.output
        assert res.stderr.startswith(f"error: {run} is in use by another rgbdslam process (pid {holder.pid}, run)")
        assert not (run / "run.json").exists()
        res = CliRunner().invoke(main, ["fuse", str(run), "-q"])  # fuse writes into the folder too
        assert res.exit_code == 2 and "is in use by another rgbdslam process" in res.stderr
    finally:
        holder.kill()  # SIGKILL: no clean-up; the kernel drops the lock
        holder.wait()
    res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK])
    assert res.exit_code == 0, res.output
    assert _status(run)["status"] == "finished"


# ----------------------------------------------------------------------------- class 5: previous/


def test_previous_is_only_replaced_when_it_holds_nothing_but_ours(desk9, tmp_path):
    run = tmp_path / "run"
    for _ in range(2):
        assert CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK]).exit_code == 0
    manifest = json.loads((run / "previous" / ".rgbdslam-manifest.json").read_text())
    assert "trajectory.tum" in manifest["entries"] and "map/mesh.ply" in manifest["entries"]
    # a user's file beside our run.json, and one inside our map/ folder: never deleted
    for mine in (run / "previous" / "thesis.tex", run / "previous" / "map" / "notes.txt"):
        mine.write_text("mine")
        res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK])
        assert res.exit_code == 2 and res.stderr.count("\n") == 1
        assert f"{mine} is in the way: rgbdslam did not write it" in res.stderr
        assert mine.read_text() == "mine" and _status(run)["status"] == "finished"
        mine.unlink()
    assert CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK]).exit_code == 0


def test_tables_written_into_a_run_folder_stay_listed_when_the_run_moves_to_previous(desk9, tmp_path):
    """A batch's (or sweep's) results tables written beside a single run's files: the next run moves
    only the run's files and their manifest entries to previous/; the tables stay listed as ours
    in the folder, so the batch may write them again."""
    from rgbdslam.batch import SUMMARY_FILES
    from rgbdslam.io.manifest import record_tables, tables_ready

    run = tmp_path / "run"
    assert CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK]).exit_code == 0
    tables_ready(run, SUMMARY_FILES)  # what a batch does around writing its tables
    for name in SUMMARY_FILES:
        (run / name).write_text("first tables\n")
    record_tables(run, SUMMARY_FILES)
    for _ in range(2):  # the second time previous/ (the first run) is replaced as well
        res = CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK])
        assert res.exit_code == 0, res.output
        tables_ready(run, SUMMARY_FILES)  # no InputError: still the batch's own tables
        here = json.loads((run / ".rgbdslam-manifest.json").read_text())["entries"]
        before = json.loads((run / "previous" / ".rgbdslam-manifest.json").read_text())["entries"]
        assert all(here[name] == "table" and name not in before for name in SUMMARY_FILES)
        assert before["trajectory.tum"] == "run" and here["trajectory.tum"] == "run"
        assert not any(k.startswith("previous") for k in before)
    assert (run / "summary.csv").read_text() == "first tables\n"


# ----------------------------------------------------------------------------- class 7: disk full


def test_a_full_disk_is_one_line_naming_the_file_and_never_a_finished_run(desk9, tmp_path):
    """Files may grow to 500 kB only (RLIMIT_FSIZE: a full disk for every file, without root): map.npz
    (~340 kB with the landmark map) is written, the map's PLY files (~1-2 MB) cannot be. One error line
    naming map/mesh.ply, no library spam, run.json not 'finished', the trajectory written before it intact,
    and no map half made (the landmark map's top view, written before the fused map, is all map/ holds)."""
    run = tmp_path / "run"
    res = subprocess.run([sys.executable, "-c", LIMITED_FSIZE, str(500_000), "run", str(desk9), "--out", str(run),
                          *QUICK], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    assert "RPly" not in res.stderr and "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if not ln.startswith(("preset ", "camera "))]  # the run's start
    assert len(lines) == 1 and lines[0].startswith(f"error: {run / 'map'}/"), res.stderr
    assert ": File too large; " in lines[0] and ".fusing" not in lines[0]  # the map file, not our temporary one
    s = _status(run)
    assert s["status"] == "failed" and s["stopped_during"] == "map" and ".ply" in s["error"]
    assert len((run / "trajectory.tum").read_text().splitlines()) == 10  # header + 9 poses
    assert not (run / "map").exists() or {p.name for p in (run / "map").iterdir()} <= {"landmarks_topview.png"}


# ----------------------------------------------------------------------------- class 9: small ones


def test_path_arguments_that_cannot_work_are_one_line(desk9, tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    gt = tmp_path / "gt.tum"
    gt.write_text("1 0 0 0 0 0 0 1\n2 1 0 0 0 0 0 1\n3 2 0 0 0 0 0 1\n")
    graph = tmp_path / "g.g2o"
    graph.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    cases = [
        (["run", str(desk9), "--out", ""], "must not be empty"),
        (["run", str(desk9), "--out", str(afile / "sub")], f"{afile}: is a file, not a folder"),
        (["evaluate", str(gt), str(tmp_path)], f"{tmp_path} is a folder, not a trajectory file"),
        (["evaluate", str(gt), str(gt), "--no-plots", "--json", str(afile / "x.json")],
         f"{afile}: is a file, not a folder"),
        (["evaluate", str(gt), str(tmp_path / "new\nline.tum")], "new\\nline.tum"),
        (["posegraph", "optimize", str(graph), "-q", "--out", str(tmp_path)], f"{tmp_path}: is a folder, not a file"),
    ]
    for args, message in cases:
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 2, (args, res.output)
        lines = res.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), (args, res.stderr)
        if message:
            assert message in lines[0], (args, lines[0])
        assert ".tmp" not in lines[0] and "/." not in lines[0], lines[0]  # never one of our temporary names


def test_a_groundtruth_that_is_a_folder_or_a_link_loop_is_not_ignored(desk9, tmp_path):
    seq = tmp_path / "rgbd_dataset_freiburg1_x"
    seq.mkdir()
    for name in ("rgb", "depth", "rgb.txt", "depth.txt"):
        (seq / name).symlink_to(desk9 / name)
    (seq / "groundtruth.txt").mkdir()
    res = CliRunner().invoke(main, ["info", str(seq)])
    assert res.exit_code == 2 and "groundtruth.txt is a folder" in res.stderr, res.output
    (seq / "groundtruth.txt").rmdir()
    (seq / "groundtruth.txt").symlink_to(seq / "loop.txt")
    (seq / "loop.txt").symlink_to(seq / "groundtruth.txt")
    res = CliRunner().invoke(main, ["info", str(seq)])
    assert res.exit_code == 2 and "groundtruth.txt" in res.stderr and res.stderr.count("\n") == 1, res.output


def test_a_killed_fusion_leaves_no_temporary_folder_behind(desk9, tmp_path):
    run = tmp_path / "run"
    assert CliRunner().invoke(main, ["run", str(desk9), "--out", str(run), *QUICK]).exit_code == 0
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = run / "map" / f".fusing-{dead.pid}-abc"
    stale.mkdir()
    (run / "map" / ".fusing-legacy").mkdir()
    assert CliRunner().invoke(main, ["fuse", str(run), "-q"]).exit_code == 0
    assert not [p for p in (run / "map").iterdir() if p.name.startswith(".fusing-")]


@pytest.mark.parametrize("text", ["[" * 100000 + "]" * 100000, '{"frames": ' + "9" * 120000 + "}"])
def test_a_run_json_nested_too_deeply_or_with_a_huge_number_is_one_line(tmp_path, text):
    from tests.conftest import cli

    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "run.json").write_text(text)
    res = cli(["fuse", tmp_path / "run"])
    assert res.exit_code == 2 and res.stderr == (f"error: {tmp_path / 'run' / 'run.json'} is not a run file rgbdslam "
                                                 f"wrote (nested too deeply or a number too long); re-run `rgbdslam "
                                                 f"run` to rewrite it\n"), res.output[-500:]

