"""SSM Studio engine: shape-model building, fitting and evaluation (no Qt in here)."""

__version__ = "0.1.0"
