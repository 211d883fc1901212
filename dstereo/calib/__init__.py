"""Camera calibration: closed-form start, full-set and batched subset solves, uncertainty."""
