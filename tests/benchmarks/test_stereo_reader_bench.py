"""benchmarks/stereo_reader.py: two trees A/B on a small synthetic stereo sequence, in child processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent.parent


def test_reader_ab_times_every_step_and_compares_the_trajectories(tmp_path):
    from rgbdslam.datasets.synthetic_stereo import generate_stereo_sequence

    seq = tmp_path / "stereo"
    generate_stereo_sequence(seq, 0.12, "kitti", frames=8, motion="xyz", noise=True, seed=1)
    out = subprocess.run([sys.executable, "-m", "benchmarks.stereo_reader", "--trees", str(ROOT), str(ROOT),
                          "--reps", "1", "--sequence", str(seq), "--config", "default", "--work", str(tmp_path / "w"),
                          "--json", str(tmp_path / "r.json")], cwd=ROOT, capture_output=True, text=True, check=True)
    rounds = json.loads((tmp_path / "r.json").read_text())["rounds"]
    assert len(rounds) == 1 and rounds[0]["identical"]  # one tree against itself: the same trajectory file
    for side in ("old", "new"):
        r = rounds[0][side]
        assert all(r[k] > 0 for k in ("read", "left", "right_orb", "match", "refine", "stereo", "load", "run"))
        assert r["load"] > r["stereo"] and r["load"] > r["read"] + r["left"]  # the whole contains its steps
        assert Path(r["trajectory"]).stat().st_size > 0
    assert "| **`Sequence.load` in all** |" in out.stdout
    assert "byte-identical in 1 of 1 rounds" in out.stdout
