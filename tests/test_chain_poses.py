"""The per-frame chain's poses, bit for bit, on fr1/rpy head200 (every frame through ``SLAM.track``,
then ``SLAM.finish``): a guard for refactors of the chain (``rgbdslam/slam.py``, the stage protocol,
the landmark stage), which must not move a single pose.

``GOLDEN`` holds, per configuration, the SHA-256 of the odometry poses and of the final poses (each
the (N, 4, 4) float64 array in C order, little-endian bytes) and the frame count. They were written by
``python -m tests.test_chain_poses`` (``RGBDSLAM_DATA`` pointing at the shared data), and the same
computation on the code before the stage protocol and the removal of 22 landmark keys (main
``0dc35c1``) gave the same digests; they were regenerated since for the depth-edge
refit of the registration, for its default window (radius 2, 15 % jump), for the landmark
map's covisibility local map, for the Kinect's full depth range (`matching.max_depth` and
`landmarks.max_depth` 10 m), for the fusion without the consistency scale and for the landmark map
pose refitted from the registration's inliers (RANSAC only when they are too few) (changes meant to move poses). A change that is *meant* to move poses
regenerates them with the same command and says so in its commit.

``default`` is the landmark map (``landmarks.enabled`` true) and ``thesis`` the preset of the
frame-to-frame chain without it: when the landmark map became the default, the regenerated
``default`` digests were exactly the former ``landmarks.enabled=true`` ones and ``thesis``'s exactly
the former default's (the flip moved no pose of either chain on fr1/rpy, a registered camera)."""

from __future__ import annotations

import hashlib
import sys

import numpy as np
import pytest

# name -> (preset or None, --set overrides); "default" is the landmark map, "thesis" the frame-to-frame chain
CONFIGS = {
    "default": (None, []),
    "thesis": ("thesis", []),
}

GOLDEN = {
    "default": (200, "42806cbc97de57f0346f5945f03dff35d0f254d29bc40258048b7a7f7d873a2a",
               "de07d648196944b548af56e3b0501205667fb2fd6469bc3a286c4a1834de641f"),
    "thesis": (200, "fd2b13f8ef03999b28f38a959b916b0985d54d008a745a684b27d92b3bf6e70b",
              "e227cf9b7a3889a99122233cc5814ce0fa250367863040336cd81c5a3cf7841b"),
}


def _digest(poses: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(poses, dtype="<f8").tobytes()).hexdigest()


def chain_poses(sequence, preset: str | None, sets: list[str]) -> tuple[int, str, str]:
    """(frames, odometry digest, final digest) of one run of ``sequence`` with ``preset`` and the overrides ``sets``."""
    from rgbdslam.config import load_config
    from rgbdslam.datasets import open_sequence
    from rgbdslam.slam import SLAM

    cfg = load_config(preset, ["mapping.enabled=false", *sets])
    seq = open_sequence(sequence, cfg.dataset)
    slam = SLAM(cfg, seq.camera)
    for i in range(len(seq)):
        slam.track(seq[i])
    odo = slam.odometry().poses
    final = slam.finish().poses
    return len(odo), _digest(odo), _digest(final)


@pytest.mark.data
@pytest.mark.slow
@pytest.mark.parametrize("name", list(CONFIGS))
def test_chain_poses_are_bit_identical_to_the_recorded_ones(rpy200, name):
    assert chain_poses(rpy200, *CONFIGS[name]) == GOLDEN[name]


def test_digest_sees_the_last_bit():
    """The digest tells apart poses one unit in the last place apart (so the test above cannot pass
    on a pose that moved by rounding)."""
    P = np.tile(np.eye(4), (3, 1, 1))
    Q = P.copy()
    Q[2, 0, 3] = np.nextafter(0.0, 1.0)
    assert _digest(P) == _digest(P.copy()) and _digest(P) != _digest(Q)


if __name__ == "__main__":  # python -m tests.test_chain_poses: print GOLDEN for the code as it is
    from tests.conftest import TUM_RPY200

    print("GOLDEN = {")
    for name, (preset, sets) in CONFIGS.items():
        print(f"    {name!r}: {chain_poses(TUM_RPY200, preset, sets)!r},")
        sys.stdout.flush()
    print("}")
