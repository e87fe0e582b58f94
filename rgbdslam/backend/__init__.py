"""The SLAM back end: the GTSAM pose graph over keyframes (``slam_graph.KeyframeGraph``)."""
