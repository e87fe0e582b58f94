"""Evaluation: timestamp association, ATE, RPE, plots and reports (no CLI code here).

Metric maths (associate, ate, rpe) are pure NumPy functions on Trajectory objects;
report.py composes them and writes JSON / plots; plots.py only draws.
"""

from rgbdslam.evaluation.associate import associate
from rgbdslam.evaluation.ate import AteResult, align, ate
from rgbdslam.evaluation.rpe import RpeResult, rpe

__all__ = ["associate", "align", "ate", "AteResult", "rpe", "RpeResult"]
