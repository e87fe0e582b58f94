"""rgbdslam: RGB-D visual SLAM in Python."""

__version__ = "0.1.0"
