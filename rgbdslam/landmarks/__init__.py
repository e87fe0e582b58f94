"""The persistent landmark map (spec §6): landmarks, their Kalman filter, the landmark store and
tracking against the map."""
