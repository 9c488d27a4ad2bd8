"""``python -m colmap_guided localize``: its subcommand's arguments and its run."""

from __future__ import annotations

import argparse
from pathlib import Path

from .. import localize as package
from ..cli import add_matcher_flags, matcher_options
from ..conf import add_conf_flags, conf_from_flags
from ..log import add_verbosity_flags

MATCHER_FLAGS = ["weights", "device"]  # localize keeps the matcher's ratio


def add_parser(subparsers) -> None:
    """The ``localize`` subcommand in ``subparsers`` (of ``argparse``'s ``add_subparsers``)."""
    loc = subparsers.add_parser(
        "localize",
        help="where was this photo taken? new photos localized in a reconstruct workspace's model",
    )
    loc.add_argument(
        "workspace", type=Path, help="the --output folder of a reconstruct run (holds sparse/N)"
    )
    loc.add_argument(
        "photos", type=Path, nargs="+", help="photos, or folders of photos, to localize (only read)"
    )
    loc.add_argument(
        "--add",
        action="store_true",
        help="also write WORKSPACE/sparse_localized/0: the "
        "model with the placed photos added (sparse/N is kept)",
    )
    loc.add_argument(
        "--model",
        type=int,
        default=0,
        help="the model to place them in: sparse/N (default 0, the largest; report.json lists all)",
    )
    # its retrieval's k and, as reconstruct's, the matcher, its weights and device
    add_conf_flags(loc, package, ["num_images"])
    add_matcher_flags(loc, MATCHER_FLAGS)
    add_verbosity_flags(loc)
    loc.set_defaults(run=run)


def run(args: argparse.Namespace) -> None:
    """The photos of ``args`` localized; the summary printed."""
    matcher_conf = {k: v for k, v in matcher_options(args, MATCHER_FLAGS).items() if v is not None}
    conf = conf_from_flags(args, package, ["num_images"])
    out = package.localize(
        args.workspace,
        args.photos,
        args.matcher,
        matcher_conf,
        conf,
        add=args.add,
        model=args.model,
    )
    print(package.summary_text(out))
