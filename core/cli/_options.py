"""Command-line options shared by several commands (not a command itself)."""

from __future__ import annotations

import argparse

from core.pipeline import ALIGN_METHODS, TRANSFORMS


def add_preparation_options(parser: argparse.ArgumentParser) -> None:
    """``--correspond``, ``--align`` and ``--transform``: how input meshes become aligned shapes."""
    parser.add_argument("--correspond", action="store_true",
                        help="inputs are raw meshes: establish correspondence first")
    parser.add_argument("--align", choices=ALIGN_METHODS, default="sync",
                        help="alignment: sync (default), gpa or none")
    parser.add_argument("--transform", choices=TRANSFORMS, default="similarity",
                        help="alignment transform class (default similarity)")
