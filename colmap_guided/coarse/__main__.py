"""``python -m colmap_guided.coarse IMG_A IMG_B --out flow.png``: see ``viz.main``."""

import sys

from colmap_guided.coarse.viz import main

if __name__ == "__main__":
    sys.exit(main())
