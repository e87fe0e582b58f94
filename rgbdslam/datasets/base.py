"""The one small interface every sequence reader implements."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from rgbdslam.frame import Frame, as_rgb, depth_warning  # noqa: F401  (the readers' record, here for them)
from rgbdslam.geometry.camera import Camera
from rgbdslam.io.trajectory import Trajectory


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
    camera_setup: Any = None  # datasets.camera_file.CameraSetup: the camera, where it came from, depth registration
    # one line on a conversion the reader applies to the ground truth (ICL-NUIM's y-up world), or None;
    # run, info and evaluate print it
    groundtruth_convention: str | None = None
    streaming: bool = False  # a live stream: length unknown until it ends, frames only through prefetched()
    # load() may run in several threads at once (no shared mutable state; OpenCV objects per thread):
    # prefetched() then prepares frames in up to ``workers`` threads, in order
    parallel_load: bool = False
    # the reader finds the key points itself (features.n_features of them) and its depth holds only
    # theirs (sparse stereo): the landmark map cannot be given more (landmarks.n_features is ignored)
    own_key_points: bool = False
    rig: Any = None  # stereo sources: the rectified geometry.stereo.StereoRig (depth from the pair); None for RGB-D

    @property
    @abstractmethod
    def timestamps(self) -> np.ndarray:
        """Timestamps (N,) of the frames, in order."""

    @abstractmethod
    def load(self, i: int) -> Frame:
        """Read frame ``i`` from disk (raises InputError naming the file if unreadable)."""

    def configure(self, cfg, purpose: str = "track") -> None:
        """Take what the reader needs from the whole config (``cfg``, a :class:`Config`) besides its
        dataset section; ``purpose``: "track" or "map". Nothing for most readers (a stereo reader takes
        its depth method)."""

    def groundtruth(self) -> Trajectory | None:
        """The ground-truth trajectory if the sequence has one."""
        return None

    def groundtruth_path(self) -> Path | None:
        """The file the ground truth comes from, as `evaluate --json` names it (default: the folder's
        groundtruth.txt; a reader whose ground truth is elsewhere says where)."""
        return Path(self.root) / "groundtruth.txt"

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

    def prefetched(self, ahead: int = 4, then: Callable[[Frame], Frame] | None = None, workers: int = 1
                   ) -> Iterator[tuple[int, Future | _Deferred]]:
        """``(i, future)`` for every frame in order; ``future.result()`` is ``load(i)`` (or raises
        its error). One background thread reads up to ``ahead`` frames in advance, so image
        decoding (cv2.imread releases the GIL) overlaps the caller's work on the previous frame.
        ``ahead = 0`` reads each frame when its ``result()`` is asked for. Frames are read in order by a
        single thread, so ``load`` need not be thread-safe — unless the sequence says it is
        (``parallel_load``): then up to ``workers`` threads (at most ``ahead``) prepare consecutive
        frames at once (stereo: two ORB extractions and the row matching per pair, mostly in
        OpenCV/NumPy without the GIL); the futures still come in frame order. Leaving the loop early (break,
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
        threads = max(1, min(workers, ahead)) if self.parallel_load else 1
        pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="frame-reader")
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
