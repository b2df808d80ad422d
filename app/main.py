"""Entry point of the ``ssm-studio`` command.

``ssm-studio`` alone opens the segmentation workspace on the demo data; ``ssm-studio view IMAGE
[--model M] [--session S]`` opens given files; every other subcommand is an engine command from
``core.cli`` and runs without importing Qt. ``--screenshot out.png`` renders the window to a
PNG and exits; with no display it re-runs itself under a virtual X server (``xvfb-run``),
because Qt's offscreen platform cannot render the OpenGL views.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys

from core import __version__
from core.cli import add_commands, requested_command, run_command


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The program's parser. Given the command line, only the engine command it runs is
    imported (or none, for the GUI): the listing in ``--help`` needs them all."""
    parser = argparse.ArgumentParser(
        prog="ssm-studio",
        description="Shape-model-based interactive segmentation of deep brain structures. "
                    "Without a command, opens the segmentation workspace on the demo data.",
    )
    parser.add_argument("--version", action="version", version=f"ssm-studio {__version__}")
    _add_gui_options(parser)
    sub = parser.add_subparsers(title="commands", metavar="COMMAND")
    view = sub.add_parser("view", help="open an image (and optionally a model or a session) in the GUI",
                          description="Open an image in the segmentation workspace.")
    view.add_argument("image", nargs="?", help="image: .nii/.nii.gz, .nrrd/.nhdr, .mha/.mhd, or a "
                                                "DICOM series (its folder or one of its files)")
    view.add_argument("--series", metavar="UID", help="DICOM folder with several series: which one")
    view.add_argument("--model", help="shape model file (.npz, or statismo/Scalismo .h5)")
    view.add_argument("--session", help="session file (.json) to restore")
    _add_gui_options(view, suppress=True)
    view.set_defaults(_command="view")
    tour = sub.add_parser("demo", help="play the demo tour in the GUI (any key stops it)",
                          description="Open the demo data and play a scripted session: contours "
                                      "drawn slice by slice with the live refit, a factor "
                                      "slider sweep, an export. Any key stops the tour.")
    tour.add_argument("--record", metavar="DIR",
                      help="write the frames as PNG files into DIR and quit at the end")
    tour.set_defaults(_command="demo")
    if argv is None or not _runs_the_gui(argv):
        add_commands(sub, only=None if argv is None else requested_command(argv))
    return parser


def _runs_the_gui(argv: list[str]) -> bool:
    """Whether the command line opens the window (no command, ``view`` or ``demo``): then no
    engine command needs importing. Help, or anything else, lists or checks them all."""
    values_of = {"--screenshot", "--tab"}
    tokens = iter(argv)
    for token in tokens:
        if token in ("-h", "--help"):
            return False
        if token in values_of:
            next(tokens, None)
        elif not token.startswith("-"):
            return token in ("view", "demo")
    return True


def _add_gui_options(parser: argparse.ArgumentParser, suppress: bool = False) -> None:
    default = argparse.SUPPRESS if suppress else None
    parser.add_argument("--screenshot", metavar="PNG", default=default,
                        help="render the main window to this PNG file and exit")
    parser.add_argument("--tab", choices=["segment", "build"], default=default,
                        help="workspace to show first (default: segment)")


def _needs_virtual_display() -> bool:
    return sys.platform.startswith("linux") and not os.environ.get("DISPLAY") \
        and not os.environ.get("WAYLAND_DISPLAY") and not os.environ.get("SSM_STUDIO_IN_XVFB")


def _rerun_under_xvfb(argv: list[str]) -> int:
    xvfb = shutil.which("xvfb-run")
    if xvfb is None:
        print("ssm-studio: error: no display, and xvfb-run is not installed to provide a virtual "
              "one (apt-get install xvfb xauth)", file=sys.stderr)
        return 2
    env = dict(os.environ, SSM_STUDIO_IN_XVFB="1", QT_QPA_PLATFORM="xcb")
    cmd = [xvfb, "-a", "-s", "-screen 0 1600x1000x24", sys.executable, "-m", "app.main", *argv]
    return subprocess.call(cmd, env=env)


def main(argv: list[str] | None = None) -> int:
    """The ``ssm-studio`` program: an engine command, or the GUI."""
    from core.cli import exit_if_interrupted

    return exit_if_interrupted(_main(argv), as_program=argv is None)


def _main(argv: list[str] | None = None) -> int:
    from core.cli import attach_negative_lists
    from core.runtime.parallel import Terminated, termination_signals

    argv = attach_negative_lists(list(sys.argv[1:] if argv is None else argv))
    try:  # a signal while the commands are imported is not lost (nor a traceback)
        with termination_signals():
            args = build_parser(argv).parse_args(argv)
    except KeyboardInterrupt:
        return 130
    except Terminated as exc:
        return exc.exit_code
    if hasattr(args, "_run"):  # an engine command: no Qt
        return run_command(args)
    screenshot = getattr(args, "screenshot", None)
    record = getattr(args, "record", None)
    if _needs_virtual_display():
        if screenshot or record:
            return _rerun_under_xvfb(argv)
        print("ssm-studio: no display found. Run it on a desktop, or render the window with "
              "'ssm-studio --screenshot out.png'.", file=sys.stderr)
        return 2
    from app.window import run_gui

    return run_gui(
        image=getattr(args, "image", None),
        model=getattr(args, "model", None),
        session=getattr(args, "session", None),
        screenshot=screenshot,
        tab=getattr(args, "tab", None) or "segment",
        series=getattr(args, "series", None),
        tour=getattr(args, "_command", None) == "demo",
        record=record,
    )


if __name__ == "__main__":
    sys.exit(main())
