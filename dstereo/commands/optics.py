"""`dstereo optics`: placeholder replaced by the optics calculator."""
