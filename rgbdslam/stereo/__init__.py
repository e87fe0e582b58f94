"""stereo stage: depth from a rectified pair (depth.py) and its config section (config.py)."""
