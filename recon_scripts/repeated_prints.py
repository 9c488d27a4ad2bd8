"""Which verified pairs of a database the card anatomy calls one print twice, and how close the
other pairs come: the similarity fit (cards.print_fit) of every pair with enough inliers.

    python -m recon_scripts.repeated_prints DATABASE [DATABASE ...] [--top 5]

Per database: the pairs grouped as repeated prints (cards.is_same_print), then the ``--top`` other
pairs with the highest share of inliers one similarity explains (the margin to the threshold).
"""

from __future__ import annotations

from pathlib import Path

from colmap_guided import cards
from recon_scripts import script_parser


def main() -> None:
    parser = script_parser(__doc__)
    parser.add_argument("databases", nargs="+", type=Path)
    parser.add_argument("--top", type=int, default=5)
    args = parser.parse_args()
    conf = cards.check_conf(None)
    for database in args.databases:
        fits, _ = cards.print_fits(database, conf)
        same = [f for f in fits if cards.is_same_print(f[2], conf)]
        others = sorted(
            (f for f in fits if not cards.is_same_print(f[2], conf)),
            key=lambda f: -f[2]["inlier_ratio"],
        )
        print(f"{database}: {len(fits)} pairs with >= {conf['min_print_inliers']} inliers")
        for kind, rows in (("same print", same), ("closest other", others[: args.top])):
            for a, b, fit in rows:
                print(f"  {kind}: {Path(a).name} ~ {Path(b).name}  {fit}")


if __name__ == "__main__":
    main()
