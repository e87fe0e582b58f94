"""File formats: TUM trajectories and atomic writes."""
