"""The offline pose-graph tool (``rgbdslam posegraph ...``): the graph model and its files,
initial guesses (odometry, spanning tree, MASAT, weighted MASAT, LAGO, chordal), Gauss–Newton,
and the MASAT paper's benchmark protocol. Works on files alone; the SLAM back end
(:mod:`rgbdslam.backend.slam_graph`) uses its MASAT, graph model and g2o writer.

Imports run one way: graph → graph_io, masat → factors, convergence → gn2d, chordal2d →
initializers, optimize → commands, bench.
"""
