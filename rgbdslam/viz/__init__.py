"""Visualisation: Rerun recordings of runs (rerun_log.py)."""
