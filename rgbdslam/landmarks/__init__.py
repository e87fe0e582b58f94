"""The persistent landmark map (spec §6): landmarks, their Kalman filter, the landmark store,
tracking against the map and the windowed local bundle adjustment."""
