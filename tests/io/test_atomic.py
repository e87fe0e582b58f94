"""Atomic writes (rgbdslam.io.atomic) and what they must never do: replace a device, a FIFO or
the link a user pointed an output at with a plain file (issue 16, class 2)."""

from __future__ import annotations

import errno
import os
import stat
import threading
from pathlib import Path

import pytest
from click.testing import CliRunner

from rgbdslam.cli import main
from rgbdslam.io.atomic import atomic_path, atomic_write_text, write_target


def _gt(tmp_path: Path) -> Path:
    p = tmp_path / "gt.tum"
    p.write_text("".join(f"{i:.1f} {0.1 * i:.3f} 0 0 0 0 0 1\n" for i in range(10)))
    return p


def _fifo_reader(path: Path) -> tuple[threading.Thread, list[bytes]]:
    got: list[bytes] = []

    def read():
        with open(path, "rb") as f:
            got.append(f.read())

    t = threading.Thread(target=read, daemon=True)
    t.start()
    return t, got


def test_a_link_stays_a_link_and_its_target_is_replaced(tmp_path):
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "out.json"
    target.write_text("old")
    link = tmp_path / "link.json"
    link.symlink_to(target)
    chain = tmp_path / "chain.json"
    chain.symlink_to(link)
    atomic_write_text(chain, "new")
    assert chain.is_symlink() and link.is_symlink() and target.read_text() == "new"
    assert sorted(p.name for p in (tmp_path / "real").iterdir()) == ["out.json"]  # no temporary left
    dangling = tmp_path / "dangling.json"
    dangling.symlink_to(tmp_path / "real" / "later.json")
    atomic_write_text(dangling, "created")
    assert dangling.is_symlink() and (tmp_path / "real" / "later.json").read_text() == "created"


def test_a_fifo_is_written_into_not_replaced(tmp_path):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    link = tmp_path / "to-pipe.json"
    link.symlink_to(fifo)
    for path in (fifo, link):
        t, got = _fifo_reader(fifo)
        atomic_write_text(path, "through the pipe\n")
        t.join(10)
        assert got == [b"through the pipe\n"]
        assert stat.S_ISFIFO(os.stat(fifo).st_mode) and link.is_symlink()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pipe", "to-pipe.json"]


def test_a_device_is_written_into_not_replaced(tmp_path):
    """/dev/null takes the bytes; a full device (a copy of /dev/full where we may make one) is
    an OSError naming the path the user gave, and the node is still a device afterwards."""
    with atomic_path("/dev/null") as tmp:
        tmp.write_bytes(b"x" * 1000)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    full = Path("/dev/full")
    if os.geteuid() == 0:  # root could replace a device node: try it on our own copy of /dev/full
        full = tmp_path / "full"
        os.mknod(full, stat.S_IFCHR | 0o666, os.makedev(1, 7))
    with pytest.raises(OSError) as e:
        atomic_write_text(full, "does not fit")
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(full)
    assert stat.S_ISCHR(os.stat(full).st_mode)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_a_folder_or_a_link_loop_is_refused_naming_it(tmp_path):
    with pytest.raises(IsADirectoryError) as e:
        write_target(tmp_path)
    assert e.value.filename == str(tmp_path)
    loop = tmp_path / "loop"
    loop.symlink_to(tmp_path / "loop2")
    (tmp_path / "loop2").symlink_to(loop)
    with pytest.raises(OSError) as e:
        atomic_write_text(loop, "x")
    assert e.value.errno == errno.ELOOP and loop.is_symlink()


def test_cli_outputs_to_devices_fifos_and_links(tmp_path):
    """evaluate --json into a FIFO (through a link, like /dev/stdout) delivers the JSON; into a
    full device it is one error line naming that path, exit 2, and the device stays a device."""
    gt = _gt(tmp_path)
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    link = tmp_path / "stdout-like"
    link.symlink_to(fifo)
    t, got = _fifo_reader(fifo)
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(gt), "--no-plots", "--json", str(link)])
    t.join(10)
    assert res.exit_code == 0, res.output
    assert got and b'"ate"' in got[0] and stat.S_ISFIFO(os.stat(fifo).st_mode) and link.is_symlink()
    full = Path("/dev/full")
    if os.geteuid() == 0:
        full = tmp_path / "full"
        os.mknod(full, stat.S_IFCHR | 0o666, os.makedev(1, 7))
    res = CliRunner().invoke(main, ["evaluate", str(gt), str(gt), "--no-plots", "--json", str(full)])
    assert res.exit_code == 2
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and str(full) in lines[0], res.output
    assert "--no-plots" not in lines[0]  # an option that does nothing is never the advice
    assert stat.S_ISCHR(os.stat(full).st_mode)
