"""Training of the coarse network's 4D filter (paper §4.2–4.3; issues 7, 17).

- ``losses``: image-level (NCNet), weak epipolar and point supervision on batched 4D volumes, and
  the image / epipolar losses from per-cell max s and argmax (shared by the dense and the sparse
  path).
- ``geometry``: F from poses, in scaled frames, induced by a homography; undistortion.
- ``scenes``: the SfM scenes (positive pairs: ≥ 30 shared 3D points, F from poses, GT from tracks).
- ``augment``: synthetic homography views, small soft scans, seeds of the archival versions.
- ``views``: network inputs (``View``), pairs (``PairSample``), grid windows.
- ``cache``: the frozen-backbone feature cache (HDF5 in ~/.cache/colmap_guided).
- ``data``: ``CoarseTrainData`` (scenes, views, cache, seeded batch sampler) and ``collate``.
- ``trainer``: resumable Adam loop on the sparse filter the CPU path runs (default) or the dense
  one, validation PCK, curves, export to safetensors.

CLI: ``python -m colmap_guided.train --supervision epipolar --out DIR [--max_minutes M] ...``
"""
