"""Command line: `python -m colmap_guided {reconstruct,localize,georeference,match,export,import,
report,coarse} ...`. Each command's parser and run function live beside its module."""

from __future__ import annotations

import argparse
import importlib
import sys

from .log import logger, set_verbosity
from .matchers import OptionError

# the modules whose ``add_parser`` adds a command (export: export and import), in --help's order
COMMANDS = (
    "reconstruct",
    "localize.command",
    "match",
    "export",
    "georeference",
    "coarse.viz",
    "html_report",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m colmap_guided",
        description="Guided feature matching for COLMAP (Darmon et al., 3DV 2020).",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        importlib.import_module(f"{__package__}.{name}").add_parser(sub)
    return parser


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["coarse"]:  # the coarse network alone: `coarse IMG_A IMG_B --out flow.png`
        from .coarse.viz import main as coarse_main

        return coarse_main(argv[1:])
    try:
        args = build_parser().parse_args(argv)
        set_verbosity(args.verbose, args.quiet)
        args.run(args)
    except OptionError as err:  # a usage error: status 1, before anything runs
        raise SystemExit(f"error: {err}") from None
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as err:
        logger.error("%s", err)
        return 2
    except OSError as err:  # a read-only or full disk: what was written so far stays consistent
        logger.error("%s; free space or fix permissions, then run the same command again.", err)
        return 2
    except KeyboardInterrupt:
        logger.error("Interrupted; run the same command again to continue from where it stopped.")
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
