"""Benchmarks and evaluation scripts of colmap_guided, run from a checkout (not installed).

    python -m recon_scripts PRESET [key=value ...]   # a benchmark preset (--help lists them)
    python -m recon_scripts.NAME [--help]             # any other script

``evaluation/`` holds what the scripts share: metrics, reference models, the historical proxy,
manifests, registration scoring and tables.
"""

import colmap_guided  # noqa: F401  (before pycolmap: see colmap_guided/__init__.py)
