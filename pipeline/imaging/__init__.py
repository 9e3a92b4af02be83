"""Image processing shared by the centroid implementations: blob detection and its background model."""
