"""SIFT keypoints and descriptors into the COLMAP database (pycolmap, COLMAP's own extractor), as
`colmap feature_extractor`.

    python -m colmap_guided.features --database_path DB --image_path DIR [--camera_mode MODE]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from colmap_guided.features import CAMERA_MODES, default_conf, extract_features


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog="python -m colmap_guided.features",
        description=" ".join(__doc__.split("\n\n")[0].split()),
    )
    parser.add_argument("--database_path", type=Path, required=True)
    parser.add_argument("--image_path", type=Path, required=True)
    parser.add_argument(
        "--camera_mode", default=default_conf["camera_mode"], choices=sorted(CAMERA_MODES)
    )
    parser.add_argument("--camera_model", default=default_conf["camera_model"])
    args = parser.parse_args(argv)
    extract_features(
        args.database_path,
        args.image_path,
        conf={"camera_mode": args.camera_mode, "camera_model": args.camera_model},
    )


if __name__ == "__main__":
    main()
