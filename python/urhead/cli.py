"""The ``urhead`` command line: one subcommand per module.

Each module in :data:`COMMANDS` defines ``add_parser(subparsers)``, which adds its
subparser and sets ``run=<function(args) -> int>`` as a default (and, optionally,
``resume_hint=<function(args) -> str>``, printed when Ctrl-C stops the command). Only the
module of the command being run is imported: the command modules import torch, which takes
seconds, and ``urhead --help`` / ``--version`` need none of it. Adding a command is one
module with that function and one line here.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from urhead import __version__

COMMANDS = {  # name: (module, one-line summary; the module's own help= says the same)
    "convert-flame": (
        "urhead.head.convert",
        "convert FLAME's generic_model.pkl / flame2023.pkl to a urhead head (.npz)",
    ),
    "synth": (
        "urhead.data.synth.subject",
        "make a synthetic ground-truth subject (ray-traced) in the VHAP layout",
    ),
    "fit": ("urhead.train.command", "fit an avatar to a subject (VHAP / GaussianAvatars layout)"),
    "fit-many": (
        "urhead.train.many",
        "fit many subjects as Ray tasks (a local Ray instance or a cluster)",
    ),
    "eval": ("urhead.use.eval_report", "score an avatar on a subject's held-out frames"),
    "render": (
        "urhead.use.render",
        "render a subject's frames side by side with the avatar, or an orbit",
    ),
    "reenact": (
        "urhead.use.reenact",
        "drive an avatar with another sequence's expression and pose (MP4 out)",
    ),
    "export": (
        "urhead.use.export",
        "export an avatar as 3DGS PLY files, textured meshes or UV maps",
    ),
}


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: X)`` to every option whose default says something: not None,
    not a store-true flag's False, and not already mentioned in the help text."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "default" in text
            or default is None
            or default is False
            or default is argparse.SUPPRESS
            or not action.option_strings
        ):
            return text
        return f"{text} (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """An argument parser whose help shows the defaults (subparsers inherit the class)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", DefaultsHelpFormatter)
        super().__init__(*args, **kwargs)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser with every command listed and ``command``'s options complete (None:
    every command complete, which imports every command module)."""
    parser = Parser(prog="urhead", description="Photoreal animatable head avatars on the CPU.")
    parser.add_argument("--version", action="version", version=f"urhead {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (module, summary) in COMMANDS.items():
        if command is None or name == command:
            importlib.import_module(module).add_parser(subparsers)
        else:
            subparsers.add_parser(name, help=summary)
    return parser


def requested_command(argv: list[str]) -> str:
    """The command named on the command line (its first word not starting with '-'), or
    "" when there is none: top-level help and argparse's errors need no command module."""
    first = next((a for a in argv if not a.startswith("-")), None)
    return first if first in COMMANDS else ""


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(requested_command(argv)).parse_args(argv)
    from urhead._memory import keep_freed_memory
    from urhead._threads import configure_threads

    try:
        configure_threads()
        keep_freed_memory()
        return int(args.run(args) or 0)
    except (ValueError, TypeError, OSError, MemoryError) as e:  # typed errors name the input
        print(f"urhead {args.command}: error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        hint = getattr(args, "resume_hint", None)
        print(
            f"\nurhead {args.command}: interrupted. "
            + (
                hint(args)
                if hint is not None
                else "Outputs are written whole, so nothing "
                "partial was left; run the same command again to redo it."
            ),
            file=sys.stderr,
        )
        return 130


if __name__ == "__main__":
    sys.exit(main())
