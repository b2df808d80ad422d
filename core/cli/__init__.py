"""Command-line interface of the engine: ``ssm-studio <command> ...`` without any Qt import.

Each module in this package is one subcommand and defines ``COMMAND`` (its name), ``HELP``
(one line), ``add_arguments(parser)`` and ``run(args) -> int``. Modules are discovered, so a
new command needs no edit here. Errors the user can fix (bad files, bad options) are printed
as one line ``ssm-studio <command>: error: <message>`` with exit code 2, never a traceback;
warnings (from our readers or from libraries) as one line ``ssm-studio <command>: warning:
<message>`` each.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import pkgutil
import re
import sys
import warnings
from collections.abc import Iterator
from types import ModuleType

from core import __version__
from core.runtime.progress import Cancelled
from core.runtime.signals import exit_now


def command_names() -> dict[str, str]:
    """Subcommand names -> module names of this package, without importing any of them (a
    command module ``mesh_labels`` holds the command ``mesh-labels``)."""
    return {info.name.replace("_", "-"): info.name for info in pkgutil.iter_modules(__path__)
            if not info.name.startswith("_")}


def requested_command(argv: list[str]) -> str | None:
    """The engine command ``argv`` runs (its first token naming one), or None. Help options
    before the command ask for the full listing, so they return None too."""
    names = command_names()
    for token in argv:
        if token in ("-h", "--help"):
            return None
        if token in names:
            return token
    return None


def command_modules(only: str | None = None) -> dict[str, ModuleType]:
    """Subcommand modules of this package by command name; with ``only``, just that one
    (importing every command costs about a second of start-up: scipy.spatial, VTK, ...)."""
    modules = command_names()
    if only is not None:
        modules = {only: modules[only]}
    found = {}
    for module_name in modules.values():
        module = importlib.import_module(f"{__name__}.{module_name}")
        if hasattr(module, "COMMAND") and hasattr(module, "run"):
            found[module.COMMAND] = module
    return dict(sorted(found.items()))


def add_commands(subparsers: argparse._SubParsersAction, only: str | None = None) -> None:
    """Register the engine subcommands on ``subparsers``: every one, or just ``only``."""
    for name, module in command_modules(only).items():
        parser = subparsers.add_parser(name, help=module.HELP, description=module.__doc__)
        module.add_arguments(parser)
        parser.set_defaults(_run=module.run, _command=name)


@contextlib.contextmanager
def one_line_warnings(command: str) -> Iterator[None]:
    """Show each warning as ``ssm-studio <command>: warning: <message>`` (once), not as
    Python's two-line report with a source line."""
    shown: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None):
        text = " ".join(str(message).split())
        if text not in shown:
            shown.add(text)
            print(f"ssm-studio {command}: warning: {text}", file=sys.stderr)

    previous = warnings.showwarning
    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


_NUMBER = r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?"
_NEGATIVE_LIST = re.compile(rf"-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?(,{_NUMBER})+")


def attach_negative_lists(argv: list[str]) -> list[str]:
    """``--placement -22.4,29.2,29.2`` as ``--placement=-22.4,29.2,29.2``: argparse takes a
    value that starts with a minus for an option unless it is a single number, so coordinate
    lists (x,y,z) with a negative first value are attached to the option before them."""
    out: list[str] = []
    for token in argv:
        if (out and out[-1].startswith("--") and "=" not in out[-1]
                and _NEGATIVE_LIST.fullmatch(token)):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def run_command(args: argparse.Namespace) -> int:
    """Run a parsed subcommand, turning user-fixable errors into one-line messages."""
    from core.runtime.parallel import JobError, Terminated, termination_signals

    try:
        # SIGTERM raises Terminated; SIGINT interrupts even when the shell started us with it
        # ignored (a background job): pool workers are stopped on the way out
        with termination_signals(), one_line_warnings(args._command):
            return int(args._run(args) or 0)
    except Terminated as exc:
        print(f"\nssm-studio {args._command}: terminated", file=sys.stderr)
        return exc.exit_code
    except Cancelled:
        print(f"ssm-studio {args._command}: cancelled", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print(f"\nssm-studio {args._command}: interrupted", file=sys.stderr)
        return 130
    except JobError as exc:  # a worker-side failure (e.g. a Dask cluster lost): which job, why
        print(f"ssm-studio {args._command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except (ValueError, OSError) as exc:  # DataFileError is a ValueError
        print(f"ssm-studio {args._command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except (MemoryError, RecursionError) as exc:
        print(f"ssm-studio {args._command}: error: {type(exc).__name__} (an input declares "
              "more data, or deeper nesting, than can be handled)", file=sys.stderr)
        return 2


def _one_line(exc: BaseException) -> str:
    from core.errors import display_path

    return display_path(" ".join(str(exc).split()))


def exit_if_interrupted(code: int, as_program: bool) -> int:
    """A command stopped by SIGINT/SIGTERM (exit 130/143) that runs as the program ends here,
    without the interpreter's shutdown: that joins the process pool's management thread, which
    can wait for a worker still being started by the fork server (seconds on a fresh machine,
    before its modules are compiled), so the exit came long after the report. The report and
    the finished outputs are written by then; the fork server and its workers follow their
    parent (core.runtime.parallel)."""
    if as_program and code in (130, 143):
        exit_now(code)
    return code


def main(argv: list[str] | None = None) -> int:
    """Engine-only entry point (``python -m core.cli``)."""
    return exit_if_interrupted(_main(argv), as_program=argv is None)


def _main(argv: list[str] | None = None) -> int:
    from core.runtime.parallel import Terminated, termination_signals

    try:
        # before the commands are imported: a signal sent while they load is not lost
        with termination_signals():
            parser = argparse.ArgumentParser(prog="ssm-studio", description=__doc__)
            parser.add_argument("--version", action="version", version=f"ssm-studio {__version__}")
            argv = attach_negative_lists(list(sys.argv[1:] if argv is None else argv))
            add_commands(parser.add_subparsers(title="commands", metavar="COMMAND"),
                         only=requested_command(argv))
            args = parser.parse_args(argv)
            if not hasattr(args, "_run"):
                parser.print_help()
                return 0
            return run_command(args)
    except KeyboardInterrupt:
        return 130
    except Terminated as exc:
        return exc.exit_code
