"""Planning: AC-PC frames and trajectories, the plan report, measurements."""
