"""Cameras: calibration files (OpenCV FileStorage YAML) and stereo pairing of live frames."""
