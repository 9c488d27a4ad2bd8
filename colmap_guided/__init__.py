"""colmap_guided: coarse-network guided keypoint matching for COLMAP (Darmon et al., 3DV 2020)."""

# Must stay the first import of the package. pycolmap's wheel (4.2.1) carries and exports its own
# copy of zlib: if pycolmap is loaded before the system libz, libz's symbols bind to pycolmap's copy
# and the next PNG that Pillow writes aborts the process ("double free or corruption"). Python's zlib
# module loads the system libz first, which keeps the two apart. A script that imports pycolmap
# itself must import colmap_guided (or zlib) before it.
import zlib  # noqa: F401

__version__ = "0.1.0"
