"""colmap_guided: coarse-network guided keypoint matching for COLMAP (Darmon et al., 3DV 2020)."""

__version__ = "0.1.0"
