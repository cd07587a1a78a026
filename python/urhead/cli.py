"""The ``urhead`` command line: one subcommand per module.

Each module in :data:`COMMAND_MODULES` defines ``add_parser(subparsers)``, which adds its
subparser and sets ``run=<function(args) -> int>`` as a default. Adding a command is one
module with that function and one line here.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = (
    "urhead.head.convert",
    "urhead.data.synthetic",
    "urhead.train.command",
    "urhead.train.many",
    "urhead.use.evaluate",
    "urhead.use.render",
    "urhead.use.reenact",
    "urhead.use.export",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="urhead", description="Photoreal animatable head avatars on the CPU."
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(subparsers)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except (ValueError, TypeError, OSError) as e:  # typed input errors name the argument
        print(f"urhead {args.command}: error: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
