"""The demo: a synthetic rig and sample, calibrated and reconstructed end to end."""
