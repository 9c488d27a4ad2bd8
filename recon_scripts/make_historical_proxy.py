"""Build the offline historical proxy: sets of ../shared/data with half of each degraded +
distractors.

    python -m recon_scripts.make_historical_proxy [--output outputs/historical_proxy]
        [--split dev|test] [--sources KEY ...]

Writes OUTPUT/<scene>/images + OUTPUT/<scene>/manifest.json per source set and
OUTPUT/proxy_manifest.json (the datasets/ltll_manifest.json schema), never anything inside
../shared. Deterministic for a --seed. Then: python -m recon_scripts.eval_registration --manifest
OUTPUT/proxy_manifest.json
"""

from __future__ import annotations

import sys
from pathlib import Path

from colmap_guided.conf import at_most_zero, none_or
from colmap_guided.paths import REPO_ROOT
from recon_scripts import script_parser
from recon_scripts.evaluation import proxy

DEFAULT_OUTPUT = REPO_ROOT / "outputs" / "historical_proxy"


def main(argv=None) -> int:
    parser = script_parser(__doc__)
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument(
        "--split",
        choices=sorted(proxy.SPLITS),
        default="dev",
        help="dev: thresholds are chosen here; test: landmarks the shipped weights never saw",
    )
    parser.add_argument(
        "--sources",
        nargs="+",
        default=None,
        help="sets of ../shared/data instead of the split's (e.g. sceaux_castle)",
    )
    parser.add_argument(
        "--distractors", type=int, default=3, help="images of unrelated scenes added to each scene"
    )
    parser.add_argument(
        "--max_size",
        type=none_or(int, old_off=at_most_zero),
        default=1024,
        help="long side of every image (none = as it is)",
    )
    parser.add_argument(
        "--crop", type=float, default=0.1, help="historical images keep >= 1 - crop of each side"
    )
    parser.add_argument(
        "--max_images",
        type=none_or(int, old_off=at_most_zero),
        default=None,
        help="first N images of each set (default none = all)",
    )
    parser.add_argument(
        "--looks",
        nargs="+",
        default=list(proxy.LOOKS),
        choices=list(proxy.LOOKS),
        help="realistic prints (<scene>_realistic) and/or damaged ones (<scene>)",
    )
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:  # a folder of the user's files, or one overlapping ../shared, is refused in one line
        path = proxy.build_proxy(
            args.output,
            args.sources or proxy.SPLITS[args.split],
            looks=args.looks,
            seed=args.seed,
            n_distractors=args.distractors,
            max_size=args.max_size,
            crop=args.crop,
            max_images=args.max_images,
        )
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"Proxy manifest: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
