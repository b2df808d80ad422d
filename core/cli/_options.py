"""Command-line options shared by several commands (not a command itself)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from core.build.pipeline import ALIGN_METHODS, TRANSFORMS


def add_scheduler_option(parser: argparse.ArgumentParser) -> None:
    """``--scheduler``: run the per-shape / per-fold / per-pair jobs as Dask tasks
    (:func:`core.runtime.parallel.use_scheduler`)."""
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="run the jobs as Dask tasks on this scheduler (tcp://host:8786), or "
                             "local:N for a local cluster of N workers (default: process pool)")


def add_preparation_options(parser: argparse.ArgumentParser) -> None:
    """``--correspond``, ``--align`` and ``--transform``: how input meshes become aligned shapes."""
    parser.add_argument("--correspond", action="store_true",
                        help="inputs are raw meshes: establish correspondence first")
    parser.add_argument("--align", choices=ALIGN_METHODS, default="sync",
                        help="alignment: sync (default), sync-sparse (synchronisation on each "
                             "shape's 10 nearest: thousands of shapes), gpa or none")
    parser.add_argument("--transform", choices=TRANSFORMS, default="similarity",
                        help="alignment transform class (default similarity)")


def say_changed_formats(command: str, written: dict[str, str]) -> None:
    """One note per output whose format differs from its input's (STL cannot keep vertex
    order, .vtu/.gii.gz have no writer): written as .vtk instead."""
    for source, output in written.items():
        if Path(source).name.split(".", 1)[-1].lower() != Path(output).name.split(".", 1)[-1]:
            print(f"ssm-studio {command}: note: {output}: written as .vtk, the format of "
                  f"{Path(source).name} cannot keep the vertex order of corresponded shapes "
                  "or cannot be written", file=sys.stderr)
