"""Command-line interface of the engine: ``ssm-studio <command> ...`` without any Qt import.

Each module in this package is one subcommand and defines ``COMMAND`` (its name), ``HELP``
(one line), ``add_arguments(parser)`` and ``run(args) -> int``. Modules are discovered, so a
new command needs no edit here. Errors the user can fix (bad files, bad options) are printed
as one line ``ssm-studio <command>: error: <message>`` with exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
from types import ModuleType

from core import __version__
from core.progress import Cancelled


def command_modules() -> dict[str, ModuleType]:
    """Subcommand modules of this package by command name."""
    found = {}
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(module, "COMMAND") and hasattr(module, "run"):
            found[module.COMMAND] = module
    return dict(sorted(found.items()))


def add_commands(subparsers: argparse._SubParsersAction) -> None:
    """Register every engine subcommand on ``subparsers``."""
    for name, module in command_modules().items():
        parser = subparsers.add_parser(name, help=module.HELP, description=module.__doc__)
        module.add_arguments(parser)
        parser.set_defaults(_run=module.run, _command=name)


def run_command(args: argparse.Namespace) -> int:
    """Run a parsed subcommand, turning user-fixable errors into one-line messages."""
    try:
        return int(args._run(args) or 0)
    except Cancelled:
        print(f"ssm-studio {args._command}: cancelled", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print(f"\nssm-studio {args._command}: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError) as exc:  # DataFileError is a ValueError
        print(f"ssm-studio {args._command}: error: {exc}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    """Engine-only entry point (``python -m core.cli``)."""
    parser = argparse.ArgumentParser(prog="ssm-studio", description=__doc__)
    parser.add_argument("--version", action="version", version=f"ssm-studio {__version__}")
    add_commands(parser.add_subparsers(title="commands", metavar="COMMAND"))
    args = parser.parse_args(argv)
    if not hasattr(args, "_run"):
        parser.print_help()
        return 0
    return run_command(args)
