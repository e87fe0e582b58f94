from rgbdslam.datasets import register  # noqa
