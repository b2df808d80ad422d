"""SSM Studio engine: shape-model building, fitting and evaluation (no Qt in here)."""

from pathlib import Path

__version__ = "0.1.0"

#: The shipped demo data and model library (``resources/`` beside the packages; installed
#: editable, see ``scripts/setup.sh``): the one place its path is written.
RESOURCES_DIR = Path(__file__).resolve().parent.parent / "resources"
