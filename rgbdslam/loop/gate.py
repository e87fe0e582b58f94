"""The sharpness gate of loop closure (docs/references.md §4).

A frame is *sharp* when its number of detected descriptors is more than ``factor`` times
the median count of the previous ``window`` frames (thesis: 1.2 x the median of 20). Only
sharp frames are searched for loops, which keeps loop closure cheap and favours frames
with little motion blur.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class SharpnessGate:
    def __init__(self, factor: float = 1.2, window: int = 20, min_history: int = 5):
        self.factor = float(factor)
        self.window = max(1, int(window))
        self.min_history = max(1, int(min_history))
        self.history: deque[float] = deque(maxlen=self.window)
        self.n_seen = 0
        self.n_sharp = 0
        self.last: tuple[float, float] = (float("nan"), float("inf"))  # (measure, threshold) of the last frame

    def threshold(self) -> float:
        """The count a frame must exceed now (inf until ``min_history`` frames were seen)."""
        if len(self.history) < self.min_history:
            return float("inf")
        return self.factor * float(np.median(np.fromiter(self.history, float, len(self.history))))

    def __call__(self, n_detected: float) -> bool:
        """Judge a frame by its descriptor count, then add the count to the window."""
        threshold = self.threshold()
        sharp = n_detected > threshold
        self.last = (float(n_detected), threshold)
        self.history.append(float(n_detected))
        self.n_seen += 1
        self.n_sharp += int(sharp)
        return sharp
