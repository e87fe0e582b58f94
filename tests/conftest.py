"""Shared fixtures: where the real data lives (RGBDSLAM_DATA, default ../shared/data)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DATA = Path(os.environ.get("RGBDSLAM_DATA", REPO.parent / "shared" / "data"))
TUM_DESK9 = DATA / "tum" / "rgbd_dataset_freiburg1_desk_9frames"
TUM_RPY200 = DATA / "tum" / "rgbd_dataset_freiburg1_rpy_head200"
POSEGRAPH = DATA / "posegraph"
# the library has no default data folder of its own (an installed package has no repository
# beside it): the tests' library calls and subprocesses find it through the variable
os.environ.setdefault("RGBDSLAM_DATA", str(DATA))


_CURRENT_TEST: list = []  # the running test item (see _current_test)


@pytest.fixture(autouse=True)
def _current_test(request):
    _CURRENT_TEST.append(request.node)
    yield
    _CURRENT_TEST.pop()


def need(path: Path) -> Path:
    """``path`` if it exists. The shared data are part of the test set-up (CI has them beside the
    clone), so a missing folder fails the test: a wrong RGBDSLAM_DATA must not turn the run green
    with skips. RGBDSLAM_ALLOW_MISSING_DATA=1 skips instead (a machine without the data).

    A test that needs the data must be marked ``@pytest.mark.data`` (``pytest -m "not data"`` is
    the fast local pass without them); an unmarked one fails here."""
    if _CURRENT_TEST and _CURRENT_TEST[-1].get_closest_marker("data") is None:
        pytest.fail(f"{_CURRENT_TEST[-1].nodeid} reads the shared data: mark it @pytest.mark.data")
    if not path.exists():
        msg = f"data not found at {path}; set RGBDSLAM_DATA to the shared data folder"
        if os.environ.get("RGBDSLAM_ALLOW_MISSING_DATA") == "1":
            pytest.skip(msg)
        pytest.fail(msg + " (or RGBDSLAM_ALLOW_MISSING_DATA=1 to skip the tests that need it)")
    return path


@pytest.fixture
def desk9() -> Path:
    return need(TUM_DESK9)


@pytest.fixture
def rpy200() -> Path:
    return need(TUM_RPY200)


def cli(args):
    """Run the ``rgbdslam`` command line in-process (click's CliRunner) with ``args`` as strings."""
    from click.testing import CliRunner

    from rgbdslam.cli import main

    return CliRunner().invoke(main, [str(a) for a in args])


def assert_cli_error(res, message):
    """The CLI turned an InputError into exit code 2 and exactly ``error: message`` on stderr."""
    assert isinstance(res.exception, SystemExit) and res.exit_code == 2, (res.exception, res.output)
    assert res.stdout == ""
    assert res.stderr == f"error: {message}\n"


# ``python -c LIMITED_FSIZE LIMIT ARGS...``: the console script with files limited to LIMIT bytes
# (RLIMIT_FSIZE: a full disk for every file, without root); a write past the limit fails with EFBIG
LIMITED_FSIZE = """
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
sys.argv = ["rgbdslam"] + sys.argv[2:]
from rgbdslam._entry import main
main()
"""
