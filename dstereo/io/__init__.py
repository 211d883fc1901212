"""Edges of the system: OpenCV detection, files in and out. The core never imports cv2."""
