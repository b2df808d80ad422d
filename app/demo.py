"""Where the demo data lives: the MNI T1 template, the demo model and demo contour points.

Resources are looked up in ``<repo root>/resources`` (override with the environment variable
``SSM_STUDIO_RESOURCES``). If the resources folder has no T1 image yet, the copy of the same
template shipped inside nilearn's wheel is used. Functions return None when a file is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

from core import RESOURCES_DIR

T1_NAME = "mni_icbm152_t1_tal_nlin_sym_09a"


def resources_dir() -> Path:
    """The resources folder (``SSM_STUDIO_RESOURCES`` or the repository's ``resources/``)."""
    env = os.environ.get("SSM_STUDIO_RESOURCES")
    if env:
        return Path(env)
    return RESOURCES_DIR


def _first(candidates: list[Path]) -> Path | None:
    for path in candidates:
        if path.is_file():
            return path
    return None


def demo_image() -> Path | None:
    """The demo T1 MRI (MNI ICBM152 2009c, 1 mm)."""
    root = resources_dir()
    found = sorted(root.glob(f"{T1_NAME}*.nii*")) + sorted(root.glob(f"*/{T1_NAME}*.nii*"))
    found = [p for p in found if "_t1_" in p.name]
    if found:
        return found[0]
    try:
        import nilearn
    except ImportError:
        return None
    return _first([Path(nilearn.__file__).parent / "datasets" / "data" / f"{T1_NAME}_converted.nii.gz"])


def require_demo_image() -> Path:
    """:func:`demo_image`, or a DataFileError saying what is missing."""
    image = demo_image()
    if image is None:
        from core.io import DataFileError

        raise DataFileError(resources_dir(), "no demo image found (resources/ is incomplete "
                            "and nilearn is not installed)")
    return image


def demo_model() -> Path | None:
    """The demo shape model (``resources/demo/model.npz``)."""
    root = resources_dir()
    env = os.environ.get("SSM_STUDIO_DEMO_MODEL")
    return _first(([Path(env)] if env else []) + [root / "demo" / "model.npz"])


def demo_points() -> Path | None:
    """Demo contour points on the demo image (``resources/demo/contour_points.csv``)."""
    return _first([resources_dir() / "demo" / "contour_points.csv"])
