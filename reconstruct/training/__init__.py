"""Training of the learned baselines (``capssim train``): config, in-memory pairs, the trainer."""
