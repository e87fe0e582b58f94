"""Benchmarks of rgbdslam: one module per benchmark, each runnable as ``python -m benchmarks.NAME``.

:mod:`benchmarks.common` holds what they share: the data folders, running rgbdslam on a sequence
through its public API, its metrics through :mod:`rgbdslam.evaluation`, running the ORB-SLAM3 peer
and Open3D's RGB-D odometry on the same frames, markdown tables, and publishing a table into
``docs/benchmarks.md`` between named markers with the command and the machine above it.

Benchmarks import rgbdslam's public names only and never replace its functions at run time
(``tests/test_imports.py`` checks both); tests never load a benchmark by file path.
"""
