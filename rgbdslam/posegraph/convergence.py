"""The convergence test of pose-graph optimisation and the iteration loop both optimisers share.

Convergence (the MASAT paper §4, docs/references.md): a run converged when the χ² change
between two consecutive iterations passes the test within ``max_iter`` iterations;
``criterion="relative"`` (g2o's) or ``"absolute"`` (see :mod:`rgbdslam.posegraph.optimize`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from rgbdslam.errors import InputError
from rgbdslam.posegraph.graph import PoseGraphData

CRITERIA = ("relative", "absolute")


@dataclass
class GNResult:
    converged: bool
    iterations: int  # iterations run (for a converged run: the iteration at which the test passed)
    chi2_initial: float
    chi2_final: float
    chi2_history: list[float] = field(default_factory=list)  # χ² before iteration 1, after 1, 2, ...
    seconds: float = 0.0
    poses: np.ndarray | None = None
    failure: str = ""


def error_summary(e: BaseException, limit: int = 200) -> str:
    """One line for a solver's exception text: its first paragraph with the line breaks joined
    (GTSAM's messages start with a blank line and go on with advice and a URL).  An exception
    without text gets a generic explanation instead of an empty string."""
    text = str(e)
    para: list[str] = []
    for line in text.splitlines():
        if line.strip():
            para.append(line.strip())
        elif para:
            break
    out = " ".join(para)
    if not out:
        return "the solver gave no details (the linear system is probably singular or not positive definite)"
    return out if len(out) <= limit else out[:limit - 3].rstrip() + "..."


def name_vertices(text: str, graph: PoseGraphData) -> str:
    """GTSAM names a variable by its key, our dense vertex index: say the file's vertex id instead."""
    def sub(m):
        k = int(m.group(1))
        return f"vertex {graph.ids[k]}" if 0 <= k < graph.n_vertices else m.group(0)

    return re.sub(r"variable (\d+) \(Symbol: \d+\)", sub, text)


def check_iteration_options(max_iter, tol, allow_zero_tol: bool = False) -> None:
    """``max_iter`` >= 1 and a finite ``tol`` > 0 (else an :class:`InputError` naming the option).
    ``allow_zero_tol``: the library's ``tol=0`` (run exactly ``max_iter`` iterations) is accepted."""
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise InputError(f"--max-iter must be a whole number of at least 1, not {max_iter!r}; give e.g. --max-iter 50")
    try:
        t = float(tol)
    except (TypeError, ValueError):
        t = float("nan")
    if not (math.isfinite(t) and (t > 0 or (allow_zero_tol and t == 0))):
        raise InputError(f"--tol must be a finite number above 0, not {tol!r}; give e.g. --tol 1e-6")


def has_converged(prev: float, cur: float, tol: float, criterion: str) -> bool:
    if not (math.isfinite(prev) and math.isfinite(cur)):
        return False
    d = abs(prev - cur)
    if criterion == "absolute":
        return d < tol
    # relative; a χ² below 1 counts as 1, or a graph that fits exactly (noise-free measurements,
    # χ² ~ 1e-28 from rounding) would never pass. Noisy graphs have χ² >> 1: unaffected.
    return d < tol * max(cur, 1.0)


def iterate_until_converged(step: Callable[[], float], chi2_0: float, max_iter: int, tol: float, criterion: str,
                            callback: Callable[[int, float], None] | None = None):
    """Call ``step()`` (one GN iteration, returns the new χ²) until the convergence test passes,
    at most ``max_iter`` times.  A ``RuntimeError`` from ``step`` or a non-finite χ² is a failure.
    Returns ``(χ² history (entry 0 = chi2_0), converged, failure text, iterations run)``."""
    prev = chi2_0
    hist = [prev]
    it = 0
    for it in range(1, max_iter + 1):
        try:
            cur = step()
        except RuntimeError as e:
            return hist, False, f"{type(e).__name__}: {error_summary(e)}", it
        hist.append(cur)
        if callback:
            callback(it, cur)
        if not math.isfinite(cur):
            return hist, False, "non-finite chi2", it
        if has_converged(prev, cur, tol, criterion):
            return hist, True, "", it
        prev = cur
    return hist, False, "", it
