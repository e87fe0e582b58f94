"""Saved maps and sessions (docs/formats.md "map.npz", docs/slam.md "Saved maps").

* :mod:`.mapfile` — the map file: its arrays, header, version, checksum; save and load with checks;
* :mod:`.sessions` — a run with a saved map: load it into the SLAM chain (localise in it, or
  extend it), then save the run's map and say in run.json which frames are localised.
"""
