"""Dataset readers and writers (EuRoC/ASL layout, TUM trajectories)."""
