"""Benchmarks and evaluation scripts of colmap_guided, run from a checkout (not installed).

    python -m recon_scripts PRESET [key=value ...]   # --help lists the presets

``bench.py`` is the presets' base; ``matching/`` measures pairs of photos, ``registration/`` photo
sets, ``scale/`` hundreds to thousands of photos; ``evaluation/`` holds what they share: metrics,
reference models, the historical proxy, manifests, registration scoring, tables, the screenshot.
"""

import argparse

import colmap_guided  # noqa: F401  (before pycolmap: see colmap_guided/__init__.py)


def script_parser(doc: str) -> argparse.ArgumentParser:
    """A script's parser: its docstring's first paragraph as description, the rest as epilog."""
    return argparse.ArgumentParser(
        description=" ".join(doc.split("\n\n")[0].split()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=doc.split("\n\n", 1)[1] if "\n\n" in doc else None,
    )
