"""The ``output`` config section: what a run records beside its trajectory (:mod:`rgbdslam.configspec`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from rgbdslam.configspec import Key, Positive


@dataclass
class OutputConfig:
    rerun: Annotated[bool, Key("stream to a spawned Rerun viewer (needs a display)")] = False
    rerun_save: Annotated[str | None, Key("record to this .rrd file")] = None
    rerun_image_width: Annotated[int, Positive(8192, "images are logged at this width (aspect kept)")] = 320
    rerun_log_every: Annotated[int, Positive(10**6, "log images every n-th frame (poses/scalars every frame)")] = 1
    plots: Annotated[bool, Key("write the evaluation plots into RUN_DIR/plots when the sequence has ground truth")] = True
