"""The second image (T2, FLAIR, CT) shown over the first: Qt-free, evented state.

The first image (``WorkspaceState.volume``) stays the reference: its grid is the one the
segmentation is exported on, and world RAS mm of its space is where points are drawn. The
second image arrives already on that grid (``core.registration.coregistration.coregister``: rigidly
registered when the grids differ), so one slice of each covers the same pixels.

Which image is the *base* (drawn on) can be switched; it changes what is shown, never a
coordinate, so contours and points stay where they are. The base image is painted at the
bottom and the other one over it, blended with an opacity or in the alternate squares of a
checkerboard. The workspace's window/level (``state.window``, ``state.level``: what the
window/level drag, presets and Ctrl+L set) always belongs to the base image; the other
image's window is kept here and swapped in when the base changes.

Events: ``loaded`` (an image was set or removed), ``display`` (mode, opacity, squares, base or
the other image's window changed).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from app.model.events import EmitterGroup
from core.geometry.planes import SliceSampler, auto_window

MODES = ("blend", "checkerboard")
BASES = ("first", "second")


class SecondImage:
    """See the module docstring; ``workspace`` is the :class:`app.model.state.WorkspaceState`."""

    def __init__(self, workspace):
        self.workspace = workspace
        self.events = EmitterGroup(loaded=(), display=())
        self.path: Path | None = None
        self.coregistered = None              # core.registration.coregistration.CoRegistered
        self.sampler: SliceSampler | None = None
        self.mode = "blend"
        self.opacity = 0.5
        self.checker_mm = 10.0
        self.base = "first"
        self.other_window = (1.0, 0.5)        # (window, level) of the image that is not the base
        workspace.events.image.connect(self._on_reference_image)

    # -- the image -----------------------------------------------------------------------
    @property
    def loaded(self) -> bool:
        return self.sampler is not None

    @property
    def transform(self) -> np.ndarray | None:
        """Second world -> first world (4x4 RAS), or None."""
        return None if self.coregistered is None else self.coregistered.transform

    def set_image(self, coregistered, path: str | os.PathLike, edited: bool = True) -> None:
        """Show ``coregistered`` (on the first image's grid) from file ``path``; the first
        image stays the base. ``edited``: a change of the work (False: restored from the
        session file, which already holds it)."""
        volume = self.workspace.volume
        if volume is None or tuple(coregistered.volume.shape) != tuple(volume.shape):
            raise ValueError(f"{path}: the second image is not on the first image's grid")
        if self.base == "second":
            self.set_base("first")
        self.coregistered = coregistered
        self.sampler = SliceSampler(coregistered.volume)
        self.path = Path(path)
        self.other_window = auto_window(coregistered.volume.data)
        self.events.loaded()
        if edited:
            self.workspace.events.edited("second image")

    def clear(self) -> None:
        if not self.loaded:
            return
        if self.base == "second":
            self.set_base("first")
        self.coregistered, self.sampler, self.path = None, None, None
        self.events.loaded()

    def _on_reference_image(self) -> None:
        """A new first image: the second one is not on its grid any more."""
        self.base = "first"                   # the new image brought its own window
        self.coregistered, self.sampler, self.path = None, None, None
        self.events.loaded()

    # -- display -------------------------------------------------------------------------
    def set_mode(self, mode: str) -> None:
        if mode not in MODES:
            raise ValueError(f"unknown display mode {mode!r}, expected one of {MODES}")
        self.mode = mode
        self.events.display()

    def set_opacity(self, opacity: float) -> None:
        opacity = float(opacity)
        if not 0.0 <= opacity <= 1.0:
            raise ValueError(f"opacity must be between 0 and 1; got {opacity}")
        self.opacity = opacity
        self.events.display()

    def set_checker_mm(self, size_mm: float) -> None:
        size_mm = float(size_mm)
        if not size_mm > 0:
            raise ValueError(f"checkerboard squares must be larger than 0 mm; got {size_mm}")
        self.checker_mm = size_mm
        self.events.display()

    def set_base(self, base: str) -> None:
        """Make ``base`` ("first" or "second") the image drawn on: painted at the bottom, and
        the one the workspace's window/level acts on."""
        if base not in BASES:
            raise ValueError(f"unknown base image {base!r}, expected one of {BASES}")
        if base == self.base:
            return
        if base == "second" and not self.loaded:
            raise ValueError("no second image: open one first (File > Open second image)")
        state = self.workspace
        base_window = (state.window, state.level)
        self.base = base
        state.set_window(*self.other_window)
        self.other_window = base_window
        self.events.display()

    def swap_base(self) -> None:
        self.set_base("second" if self.base == "first" else "first")

    def window_of(self, which: str) -> tuple[float, float]:
        """(window, level) of the "first" or "second" image."""
        state = self.workspace
        return (state.window, state.level) if which == self.base else self.other_window

    def set_window_of(self, which: str, window: float, level: float) -> None:
        if which == self.base:
            self.workspace.set_window(window, level)
        else:
            self.other_window = (max(float(window), 1e-6), float(level))
            self.events.display()

    def value_at(self, world: np.ndarray) -> float | None:
        """The second image's intensity at a world point (its voxel on the first grid;
        None outside it or where the second image has no data)."""
        if not self.loaded:
            return None
        value = self.coregistered.volume.value_at(world)
        return None if value is None or not np.isfinite(value) else value

    def describe(self) -> str:
        """One line for the panel: file, how it was placed, what is drawn on."""
        if not self.loaded:
            return "No second image"
        c = self.coregistered
        how = (f"registered rigidly ({c.seconds:.1f} s, metric {c.metric:.3f})" if c.registered
               else "same grid as the first image" if np.allclose(c.transform, np.eye(4))
               else "placed with the session's transform")
        return f"{self.path.name}: {how}. Drawing on the {self.base} image."

    # -- sessions ------------------------------------------------------------------------
    def to_document(self) -> dict | None:
        """Path, transform and display settings for a session file (``info.second_image``)."""
        if not self.loaded:
            return None
        return {"path": os.path.abspath(self.path),
                "transform": np.asarray(self.transform).tolist(),
                "registered": bool(self.coregistered.registered),
                "mode": self.mode, "opacity": self.opacity, "checker_mm": self.checker_mm,
                "base": self.base, "first_window": list(self.window_of("first")),
                "second_window": list(self.window_of("second"))}

    def apply_display(self, document: dict) -> None:
        """The display settings of :meth:`to_document` (after its image is loaded again)."""
        if document.get("mode") in MODES:
            self.mode = document["mode"]
        self.opacity = float(np.clip(document.get("opacity", self.opacity), 0.0, 1.0))
        if float(document.get("checker_mm", 0) or 0) > 0:
            self.checker_mm = float(document["checker_mm"])
        if self.base != "first":
            self.set_base("first")
        if document.get("first_window"):
            self.workspace.set_window(*document["first_window"])
        if document.get("second_window"):
            self.other_window = tuple(float(v) for v in document["second_window"])
        if document.get("base") == "second":
            self.set_base("second")
        self.events.display()
