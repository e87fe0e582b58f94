"""The ``backend`` config section: the keyframe pose graph (:mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from rgbdslam.configspec import AtMost, Key, Positive


@dataclass
class BackendConfig:
    """GTSAM pose graph over keyframes (docs/slam.md)."""

    # upper bounds: GTSAM takes C ints for iteration counts
    enabled: Annotated[bool, Key("a graph of odometry edges only; loop.enabled (the default) builds it anyway")] = False
    init: Annotated[Literal["masat", "weighted_masat", "odometry", "spanning_tree", "isam2"], Key(
        "initial guess of the batch optimisation (MASAT, weighted MASAT, odometry, spanning tree or iSAM2's "
        "estimate)")] = "masat"
    robust_kernel: Annotated[Literal["none", "huber", "cauchy"], Key("robust kernel of the loop edges")] = "cauchy"
    kernel_width: Annotated[float, Positive(1e6, "width of the loop edges' robust kernel (whitened: sigmas)")] = 1.0
    kernel_chain_scaling: Annotated[bool, Key(
        "widen each loop's kernel by the odometry drift expected between its ends")] = True
    isam2: Annotated[bool, Key("incremental update whenever a loop edge arrives")] = True
    isam2_extra_updates: Annotated[int, AtMost(1000, "extra iSAM2 relinearisation steps after each loop")] = 4
    optimizer: Annotated[Literal["lm", "gn"], Key("final batch optimisation: Levenberg-Marquardt or Gauss-Newton")] = "lm"
    max_iterations: Annotated[int, Positive(100_000, "iterations of the final batch optimisation")] = 100
    relative_error_tol: Annotated[float, Positive(1.0,
        "the batch optimisation stops when the error changes less than this (relative)")] = 1e-6
    prior_sigma: Annotated[float, Positive(1000.0, "first keyframe's prior (rad and metres)")] = 1e-4
