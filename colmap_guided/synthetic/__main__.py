"""``python -m colmap_guided.synthetic OUT_DIR``: render the scene with its ground truth."""

from .scene import main

main()
