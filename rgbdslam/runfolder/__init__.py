"""The run folder: what ``rgbdslam run`` writes into ``--out`` and everything that reads it back
(docs/formats.md), and the rule every writing command follows (docs/outputs.md).

- :mod:`.folder`    writing a run folder: its lock, the earlier run moved to ``previous/``, run.json
                    (:class:`~.folder.RunRecord`), the trajectories and the closing summary
- :mod:`.read`      reading one: run.json with its fields checked, the config used, the trajectory
- :mod:`.depth`     the keyframe depth images (``keyframes/depth_*.png``) and their scale

What rgbdslam wrote into an output folder, so what it may replace there, is the manifest
(:mod:`rgbdslam.io.manifest`, used by every writing command). Import from the modules (``from rgbdslam.runfolder.read import read_run``).
"""
