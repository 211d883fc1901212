"""Configuration: defaults < file < flags."""
