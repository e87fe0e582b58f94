"""Camera calibrations measured from a recording itself, without ground truth (``rgbdslam calibrate``).

* :mod:`.depth_to_color`: where an unregistered depth camera's images sit in the colour images
  (colour focal length and depth-to-colour offset), by putting depth outlines onto colour edges;
  writes a camera file for ``rgbdslam run --camera``.
* :mod:`.rolling_shutter`: a camera's rolling-shutter readout time (or any other config or
  camera-file value), by how well the odometry agrees with the loop closures of full runs.
"""
