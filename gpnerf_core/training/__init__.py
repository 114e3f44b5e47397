"""Training: the loop, the optimizer set-up and checkpoints."""
