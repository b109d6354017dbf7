"""The trainer loop, optimizers and schedules, densification, checkpoints and writers."""
