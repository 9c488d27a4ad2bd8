"""colmap_guided: coarse-network guided keypoint matching for COLMAP (Darmon et al., 3DV 2020)."""

# Must stay the first import of the package. pycolmap's wheel (4.2.1) carries and exports its own
# copy of zlib: if pycolmap is loaded before the system libz, libz's symbols bind to pycolmap's copy
# and the next PNG that Pillow writes aborts the process ("double free or corruption"). Python's
# zlib module loads the system libz first, which keeps the two apart. A script that imports pycolmap
# itself must import colmap_guided (or zlib) before it.
import zlib  # noqa: F401
from importlib import metadata

__version__ = "0.1.0"
MIN_PYCOLMAP = "4.2.1"  # pyproject.toml's floor: the version tested (4.0-4.1.0 match 4-6x slower)


def _release(version: str) -> tuple[int, ...]:
    return tuple(int(part) for part in version.split("+")[0].split(".")[:3] if part.isdigit())


try:  # the installed version from its metadata: pycolmap itself is not imported here (see above)
    _pycolmap = metadata.version("pycolmap")
except metadata.PackageNotFoundError:  # then importing it says what is missing
    _pycolmap = MIN_PYCOLMAP
if _release(_pycolmap) < _release(MIN_PYCOLMAP):
    raise ImportError(
        f"colmap_guided needs pycolmap >= {MIN_PYCOLMAP}, found {_pycolmap}: "
        f"pip install -U 'pycolmap>={MIN_PYCOLMAP}'"
    )
