"""Training of the coarse network's 4D filter (paper §4.2–4.3; issue 7).

- ``losses``: image-level (NCNet), weak epipolar and point supervision on batched 4D volumes.
- ``data``: positive pairs from COLMAP models (≥ 30 shared 3D points, F from poses, GT from tracks),
  negatives across scenes, synthetic homography pairs, archival augmentation, feature cache.
- ``trainer``: resumable Adam loop, validation PCK, curves, export to safetensors.

CLI: ``python -m colmap_guided.train --supervision epipolar --out DIR [--max_minutes M] ...``
"""
