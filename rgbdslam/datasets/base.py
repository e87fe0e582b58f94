"""The one small interface every sequence reader implements."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from rgbdslam.geometry.camera import Camera
from rgbdslam.io.trajectory import Trajectory


@dataclass
class Frame:
    """One RGB-D frame as every stage sees it."""

    index: int  # position in the sequence (after stride/first_frame)
    timestamp: float  # seconds (the colour image's time stamp)
    rgb: np.ndarray  # (H, W, 3) uint8, RGB order
    depth: np.ndarray  # (H, W) float32 metres, 0 = no measurement
    camera: Camera
    name: str = ""  # e.g. the colour file's relative path, for messages


class Sequence(ABC):
    """A recorded RGB-D sequence. Frames are read lazily, one at a time."""

    name: str
    root: Path
    camera: Camera

    @property
    @abstractmethod
    def timestamps(self) -> np.ndarray:
        """Timestamps (N,) of the frames, in order."""

    @abstractmethod
    def load(self, i: int) -> Frame:
        """Read frame ``i`` from disk (raises InputError naming the file if unreadable)."""

    def groundtruth(self) -> Trajectory | None:
        """The ground-truth trajectory if the sequence has one."""
        return None

    def __len__(self) -> int:
        return len(self.timestamps)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self.load(i)

    def __getitem__(self, i: int) -> Frame:
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(i)
        return self.load(i)
