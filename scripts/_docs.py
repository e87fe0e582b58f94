"""Shared by the benchmark scripts: replace one "## " section of docs/benchmarks.md."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "docs" / "benchmarks.md"


def replace_section(section: str, path: Path = BENCHMARKS) -> None:
    """Replace the section whose first line is ``section``'s first line ("## Title") up to the
    next "## " heading, or append it; written atomically. Other sections are left alone."""
    from rgbdslam.io.atomic import atomic_write_text

    heading = section.splitlines()[0]
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    start = text.find(heading + "\n")
    if start >= 0:
        end = text.find("\n## ", start + 1)
        text = text[:start] + section.rstrip("\n") + "\n" + ("" if end < 0 else text[end:])
    else:
        text = text.rstrip("\n") + "\n\n" + section.rstrip("\n") + "\n"
    atomic_write_text(path, text)


def publish(section: str, write_docs: bool) -> int:
    """Print a benchmark's markdown section; with ``write_docs`` also put it into benchmarks.md."""
    print(section)
    if write_docs:
        replace_section(section)
    return 0


def reference_timing(reps: int = 20) -> str:
    """A fixed workload timed on this machine now, printed next to a benchmark's numbers, so that
    runs on different days (the machines are shared and their speed varies) can be compared:
    ORB (1000 features) on a seeded 640x480 texture and a 1000x1000 Hamming matrix (NumPy)."""
    import time

    import cv2
    import numpy as np

    from rgbdslam.frontend.features import descriptor_words
    from rgbdslam.frontend.matching import hamming_matrix

    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (0, 0), 1.5)
    orb = cv2.ORB_create(1000)
    words = descriptor_words(rng.integers(0, 256, (1000, 32), dtype=np.uint8))

    def median_ms(fn) -> float:
        fn()
        times = []
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return 1e3 * float(np.median(times))

    return (f"reference workload (median of {reps}): ORB on 640x480 {median_ms(lambda: orb.detectAndCompute(img, None)):.1f} ms, "
            f"1000x1000 Hamming matrix {median_ms(lambda: hamming_matrix(words, words)):.1f} ms")
