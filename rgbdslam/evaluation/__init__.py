"""Evaluation: timestamp association, ATE, RPE, plots and reports (no CLI code here).

Metric maths are pure NumPy functions on Trajectory objects:
``associate.associate``, ``ate.ate`` / ``ate.align``, ``rpe.rpe``;
``report`` composes them and writes JSON / plots; ``plots`` only draws.
(The functions are not re-exported here: ``ate``, ``rpe`` and ``associate`` would shadow
their own modules.)
"""
