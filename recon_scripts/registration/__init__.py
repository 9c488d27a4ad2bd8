"""Presets measured on photo sets: photos registered and on the reference pose, localized,
georeferenced, models joined, the pipeline end to end."""
