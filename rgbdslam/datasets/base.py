"""The one small interface every sequence reader implements."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

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
    # key points found ahead of time (frontend.features.detect, run in the reader thread), or None
    detections: Any = field(default=None, repr=False, compare=False)


class _Deferred:
    """A read that happens when its result is asked for (``Sequence.prefetched(0)``)."""

    def __init__(self, load, i: int):
        self._load, self._i = load, i

    def result(self) -> Frame:
        return self._load(self._i)


def _load_then(load: Callable[[int], Frame], then: Callable[[Frame], Frame] | None) -> Callable[[int], Frame]:
    return load if then is None else (lambda i: then(load(i)))


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

    def prefetched(self, ahead: int = 4, then: Callable[[Frame], Frame] | None = None
                   ) -> Iterator[tuple[int, Future | _Deferred]]:
        """``(i, future)`` for every frame in order; ``future.result()`` is ``load(i)`` (or raises
        its error). One background thread reads up to ``ahead`` frames in advance, so image
        decoding (cv2.imread releases the GIL) overlaps the caller's work on the previous frame.
        ``ahead = 0`` reads each frame when its ``result()`` is asked for. Frames are read in order by a
        single thread, so ``load`` need not be thread-safe. Leaving the loop early (break,
        Ctrl-C) cancels the reads not yet started. ``then`` (optional) is applied to each frame
        in the same thread, after reading: work that needs only the frame (the pipeline detects
        key points there, ``frontend.features.with_detections``); with ``ahead = 0`` it is not
        applied, as it would only move the work without overlapping it."""
        n = len(self)
        if ahead <= 0:
            for i in range(n):
                yield i, _Deferred(self.load, i)
            return
        load = _load_then(self.load, then)
        pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="frame-reader")
        pending: deque[tuple[int, Future]] = deque()
        nxt = 0
        try:
            for _ in range(n):
                while nxt < n and len(pending) < ahead:
                    pending.append((nxt, pool.submit(load, nxt)))
                    nxt += 1
                yield pending.popleft()
            pool.shutdown(wait=True)  # every read is done: let the thread end now
        finally:
            pool.shutdown(wait=False, cancel_futures=True)
