"""Low-level control shared by the gaits: joint impedance, trunk control, swing trajectories, standing."""
