"""What every writing command promises about the folders it writes into (docs/outputs.md): it
replaces only what rgbdslam's manifest says it wrote there; anything else in its way stops it with
one line naming that path (exit 2); an export never writes into or over its own run, takes the
run's lock and refuses an unfinished run; links are never followed out of an output folder; a full
disk never leaves a half-written manifest; a damaged map file is one line.

Every test here goes through the command line (click's runner, or the console script where a
library's own output on the process's stderr matters) on the shared TUM frames."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from rgbdslam.cli import main

from tests.conftest import LIMITED_FSIZE

pytestmark = pytest.mark.data

QUICK = ["-q", "--set", "output.plots=false", "--set", "mapping.map2d=false"]
MANIFEST = ".rgbdslam-manifest.json"


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _one_error_line(res, *parts):
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.stderr.splitlines() if not ln.startswith("note: ")]  # "moved to previous/"
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    for part in parts:
        assert str(part) in lines[0], (part, lines[0])
    return lines[0]


def _files(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and not p.is_symlink() and p.name != ".rgbdslam.lock"}


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """One finished run of the 9 desk frames with its map (cloud and mesh); tests copy it."""
    from tests.conftest import TUM_DESK9, need

    run = tmp_path_factory.mktemp("finished") / "run"
    res = _cli("run", need(TUM_DESK9), "--out", run, *QUICK)
    assert res.exit_code == 0, res.output
    assert (run / "map" / "mesh.ply").is_file()
    return run


def _copy(run: Path, dst: Path) -> Path:
    shutil.copytree(run, dst, symlinks=True)
    return dst


# ----------------------------------------------------------------------------- an export's source run


@pytest.mark.parametrize("fmt", ["colmap", "nerfstudio"])
def test_an_export_never_writes_over_its_own_run(finished, tmp_path, fmt):
    """The run folder is named like the format's folder and --out is its parent: the export would
    replace the run itself. Also --out inside the run (but for RUN/export) is refused."""
    run = _copy(finished, tmp_path / fmt)
    before = _files(run)
    _one_error_line(_cli("export", run, "-f", fmt, "--out", tmp_path, "-q"), f"{run} would replace the run folder")
    _one_error_line(_cli("export", run, "-f", "tum", "--out", run, "-q"), f"--out {run} is inside the run folder")
    _one_error_line(_cli("export", run, "-f", "tum", "--out", run / "map", "-q"), "is inside the run folder")
    assert _files(run) == before
    res = _cli("export", run, "-f", "tum", "-q")  # the default, RUN/export, is the run's own place for exports
    assert res.exit_code == 0, res.output
    assert (run / "export" / "trajectory.tum").read_bytes() == before["trajectory.tum"]


def test_an_export_never_replaces_a_folder_it_did_not_write(finished, tmp_path):
    out = tmp_path / "out"
    (out / "colmap").mkdir(parents=True)
    (out / "colmap" / "thesis.tex").write_text("mine")
    (out / "trajectory.tum").write_text("my own trajectory\n")
    _one_error_line(_cli("export", finished, "-f", "colmap", "--out", out, "-q"),
                    f"{out / 'colmap'} is in the way: rgbdslam did not write it")
    _one_error_line(_cli("export", finished, "-f", "tum", "--out", out, "-q"), f"{out / 'trajectory.tum'} is in the way")
    assert (out / "colmap" / "thesis.tex").read_text() == "mine"
    assert (out / "trajectory.tum").read_text() == "my own trajectory\n"
    # its own earlier export is replaced; a file a user puts into it afterwards stops the next one
    fresh = tmp_path / "fresh"
    for _ in range(2):
        res = _cli("export", finished, "-f", "colmap", "--out", fresh, "-q")
        assert res.exit_code == 0, res.output
    (fresh / "colmap" / "notes.txt").write_text("mine")
    _one_error_line(_cli("export", finished, "-f", "colmap", "--out", fresh, "-q"), fresh / "colmap" / "notes.txt")
    assert (fresh / "colmap" / "notes.txt").read_text() == "mine"
    # another run's outputs are not an export's to replace
    _one_error_line(_cli("export", finished, "-f", "tum", "--out", _copy(finished, tmp_path / "other"), "-q"),
                    "holds the outputs of `rgbdslam run`")


def test_a_run_never_replaces_an_exports_trajectory(finished, tmp_path, desk9):
    out = tmp_path / "exported"
    assert _cli("export", finished, "-f", "tum", "--out", out, "-q").exit_code == 0
    _one_error_line(_cli("run", desk9, "--out", out, *QUICK),
                    f"{out / 'trajectory.tum'} is in the way: it holds the outputs of `rgbdslam export`")


# ----------------------------------------------------------------------------- a run's artefact folders


@pytest.mark.parametrize("folder", ["map", "plots", "export", "keyframes", "sessions"])
def test_a_users_file_in_an_artefact_folder_is_never_moved_or_deleted(finished, tmp_path, desk9, folder):
    """A second run into the folder neither moves the user's file to previous/ as rgbdslam's nor
    deletes it (the third run did): it stops before anything moves, naming the file."""
    run = _copy(finished, tmp_path / "run")
    made_by_user = not (run / folder).exists()
    (run / folder).mkdir(exist_ok=True)
    mine = run / folder / "mine.txt"
    mine.write_text("mine")
    before = _files(run)
    for _ in range(2):
        line = _one_error_line(_cli("run", desk9, "--out", run, *QUICK), "is in the way: rgbdslam did not write it")
        assert line.startswith(f"error: {run / folder}")  # the file, or the folder when rgbdslam made none there
    assert _files(run) == before and not (run / "previous").exists()
    mine.unlink()
    if made_by_user:  # an empty folder the user made is theirs too
        _one_error_line(_cli("run", desk9, "--out", run, *QUICK), f"{run / folder} is in the way")
        (run / folder).rmdir()
    for _ in range(2):
        assert _cli("run", desk9, "--out", run, *QUICK).exit_code == 0
    manifest = json.loads((run / "previous" / MANIFEST).read_text())
    prev = run / "previous"
    assert manifest["complete"] and set(manifest["entries"]) == {
        p.relative_to(prev).as_posix() for p in prev.rglob("*")} - {MANIFEST}  # exactly what is there


def test_fuse_writes_beside_a_users_file_but_never_over_one(finished, tmp_path):
    run = _copy(finished, tmp_path / "run")
    (run / "map" / "notes.txt").write_text("mine")
    assert _cli("fuse", run, "-q").exit_code == 0
    assert (run / "map" / "notes.txt").read_text() == "mine"
    assert "map/notes.txt" not in json.loads((run / MANIFEST).read_text())["entries"]
    other = _copy(finished, tmp_path / "other")
    (other / "map" / "cloud.ply").unlink()
    manifest = json.loads((other / MANIFEST).read_text())
    del manifest["entries"]["map/cloud.ply"]
    (other / MANIFEST).write_text(json.dumps(manifest))
    (other / "map" / "cloud.ply").write_text("my cloud")
    _one_error_line(_cli("fuse", other, "-q"), f"{other / 'map' / 'cloud.ply'} is in the way")
    assert (other / "map" / "cloud.ply").read_text() == "my cloud"


# ----------------------------------------------------------------------------- links


def test_links_in_an_output_folder_are_never_followed_out_of_it(finished, tmp_path, desk9):
    elsewhere = tmp_path / "elsewhere.txt"
    elsewhere.write_text("precious")
    run = tmp_path / "new"
    run.mkdir()
    (run / "trajectory.tum").symlink_to(elsewhere)
    _one_error_line(_cli("run", desk9, "--out", run, *QUICK), f"{run / 'trajectory.tum'} is in the way")
    out = tmp_path / "exports"
    out.mkdir()
    (out / "poses.txt").symlink_to(elsewhere)
    _one_error_line(_cli("export", finished, "-f", "kitti", "--out", out, "-q"), f"{out / 'poses.txt'} is in the way")
    assert elsewhere.read_text() == "precious"
    # a link where the manifest lists a file of ours: moved (or replaced) as the link
    again = _copy(finished, tmp_path / "again")
    (again / "trajectory.tum").unlink()
    (again / "trajectory.tum").symlink_to(elsewhere)
    assert _cli("run", desk9, "--out", again, *QUICK).exit_code == 0
    assert (again / "previous" / "trajectory.tum").is_symlink() and elsewhere.read_text() == "precious"
    assert not (again / "trajectory.tum").is_symlink()
    assert _cli("export", finished, "-f", "kitti", "--out", tmp_path / "ex2", "-q").exit_code == 0
    (tmp_path / "ex2" / "poses.txt").unlink()
    (tmp_path / "ex2" / "poses.txt").symlink_to(elsewhere)
    assert _cli("export", finished, "-f", "kitti", "--out", tmp_path / "ex2", "-q").exit_code == 0
    assert not (tmp_path / "ex2" / "poses.txt").is_symlink() and elsewhere.read_text() == "precious"


# ----------------------------------------------------------------------------- export: lock and status

_HOLD = """
import fcntl, os, sys, time
fd = os.open(os.path.join(sys.argv[1], ".rgbdslam.lock"), os.O_RDWR | os.O_CREAT, 0o666)
fcntl.flock(fd, fcntl.LOCK_EX)  # what a run writing into the folder holds
print("locked", flush=True)
time.sleep(600)
"""


@pytest.mark.parametrize("status", ["running", "interrupted", "failed"])
def test_export_refuses_an_unfinished_run(finished, tmp_path, status):
    run = _copy(finished, tmp_path / "run")
    info = json.loads((run / "run.json").read_text())
    (run / "run.json").write_text(json.dumps({**info, "status": status}))
    _one_error_line(_cli("export", run, "-f", "tum", "-q"), f"says the run is '{status}', not finished")
    assert not (run / "export").exists()


def test_export_refuses_a_folder_a_run_is_writing_into(finished, tmp_path):
    run = _copy(finished, tmp_path / "run")
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(run)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        _one_error_line(_cli("export", run, "-f", "tum", "-q"), f"{run} is in use by another rgbdslam process")
        assert not (run / "export").exists()
    finally:
        holder.kill()
        holder.wait()
    assert _cli("export", run, "-f", "tum", "-q").exit_code == 0


# ----------------------------------------------------------------------------- a full disk, a damaged manifest


@pytest.fixture
def small_disk(tmp_path):
    """A real 16 MB file system (tmpfs; mounting needs root), unmounted afterwards."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16m", "tmpfs", str(mnt)],
                                           capture_output=True).returncode != 0:
        pytest.skip("needs root to mount a small file system")
    yield mnt
    subprocess.run(["umount", "-l", str(mnt)], check=False)


def _fill(disk: Path) -> list[Path]:
    """Fill ``disk`` to the last byte (unbuffered writes: the last one fails with ENOSPC)."""
    fillers = [disk / "filler", disk / "filler2"]
    for path, size in zip(fillers, (1 << 16, 1)):
        with open(path, "wb", buffering=0) as f:
            try:
                while True:
                    f.write(b"\0" * size)
            except OSError:
                pass
    return fillers


def test_a_full_disk_while_the_earlier_run_moves_names_a_file_and_leaves_no_empty_manifest(small_disk, desk9):
    run = small_disk / "run"
    assert _cli("run", desk9, "--out", run, *QUICK, "--no-map").exit_code == 0
    first = (run / "trajectory.tum").read_bytes()
    fillers = _fill(small_disk)
    res = _cli("run", desk9, "--out", run, *QUICK, "--no-map")
    line = _one_error_line(res, f"error: {run}/", "No space left on device")
    assert ".tmp" not in line and ".json." not in line  # a file of the run, never one of our temporary names
    empty = [p for p in run.rglob("*") if p.is_file() and p.stat().st_size == 0 and p.name != ".rgbdslam.lock"]
    assert not empty, empty
    for manifest in run.rglob(MANIFEST):
        json.loads(manifest.read_text())  # whole, never half written
    assert (run / "previous" / "trajectory.tum").read_bytes() == first
    for filler in fillers:
        filler.unlink()
    for _ in range(2):  # the folder is usable again: the earlier runs are moved and replaced as before
        assert _cli("run", desk9, "--out", run, *QUICK, "--no-map").exit_code == 0
    assert json.loads((run / "previous" / "run.json").read_text())["status"] == "finished"


def test_a_damaged_manifest_is_named_never_taken_for_a_stranger(finished, tmp_path, desk9):
    run = _copy(finished, tmp_path / "run")
    assert _cli("run", desk9, "--out", run, *QUICK).exit_code == 0  # previous/ now holds a run
    for path, content, why in [(run / "previous" / MANIFEST, "", "it is empty"),
                               (run / MANIFEST, '{"entries": ', "it is not valid JSON"),
                               (run / MANIFEST, '{"entries": {"run.json": "mine"}}', "it does not hold rgbdslam's list")]:
        good = path.read_text()
        path.write_text(content)
        _one_error_line(_cli("run", desk9, "--out", run, *QUICK), f"{path} is damaged ({why}")
        path.write_text(good)
    assert _cli("run", desk9, "--out", run, *QUICK).exit_code == 0


# ----------------------------------------------------------------------------- a damaged map, small ones


def test_a_truncated_mesh_exports_nothing_and_is_one_line(finished, tmp_path):
    run = _copy(finished, tmp_path / "run")
    mesh = run / "map" / "mesh.ply"
    data = mesh.read_bytes()
    mesh.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    exe = Path(sys.executable).parent / "rgbdslam"
    res = subprocess.run([str(exe), "export", str(run), "-f", "tum,obj,glb", "--out", str(out), "-q"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {mesh} is damaged (it is cut short"), res.stderr
    assert "RPly" not in res.stderr + res.stdout
    assert not out.exists() or not [p for p in out.iterdir() if not p.name.startswith(".rgbdslam")]


def test_export_out_empty_is_refused(finished, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _one_error_line(_cli("export", finished, "-f", "tum", "--out", "", "-q"), "must not be empty")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_during_a_folder_export_names_the_file_in_its_final_place(finished, tmp_path):
    out = tmp_path / "out"
    res = subprocess.run([sys.executable, "-c", LIMITED_FSIZE, "30000", "export", str(finished), "-f", "colmap",
                          "--out", str(out), "-q"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {out / 'colmap'}/"), res.stderr
    assert "/.colmap" not in lines[0] and "File too large" in lines[0]
    assert not [p for p in out.iterdir() if not p.name.startswith(".rgbdslam")]


def test_a_new_synthetic_sequence_never_deletes_a_users_file_in_the_old_one(tmp_path):
    seq = tmp_path / "synth"
    args = ["synth", seq, "--frames", "2", "--size", "64", "48"]
    assert _cli(*args).exit_code == 0
    mine = seq / "rgb" / "notes.txt"
    mine.write_text("mine")
    _one_error_line(_cli(*args, "--seed", "1"), f"{mine} is in the way: rgbdslam did not write it")
    assert mine.read_text() == "mine"
    mine.unlink()
    assert _cli(*args, "--seed", "1").exit_code == 0  # an earlier sequence of its own is replaced
    assert "seed: 1" in (seq / "synthetic.yaml").read_text()


def test_a_full_disk_while_rendering_a_sequence_names_the_file_in_its_final_place(tmp_path):
    seq = tmp_path / "synth"
    res = subprocess.run([sys.executable, "-c", LIMITED_FSIZE, "3000", "synth", str(seq), "--frames", "3", "--size",
                          "64", "48"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {seq / 'rgb'}/") and "File too large" in lines[0], res.stderr
    assert ".partial" not in lines[0] and not seq.exists() and list(tmp_path.iterdir()) == []
