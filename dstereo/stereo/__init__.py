"""Reconstruction from a calibrated pair: rectify, search range, disparity, sub-pixel, triangulate, disparity noise, the pipeline."""
