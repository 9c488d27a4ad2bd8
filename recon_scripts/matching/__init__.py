"""Presets measured on pairs of photos: two-view pose, verified pairs, the coarse flow,
retrieval."""
