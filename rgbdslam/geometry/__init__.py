"""SE(3)/SO(3) helpers, the closed-form rigid fit and the camera model."""
