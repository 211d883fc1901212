"""The depth-of-field and optics calculator."""
