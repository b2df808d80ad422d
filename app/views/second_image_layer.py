"""The slice views' layer that shows the second image with the first (blend or checkerboard).

Both images are on the first image's grid (:mod:`app.model.second_image`), so the view's slice of
the first image and this layer's slice of the second cover the same pixels. Each is windowed
with its own window/level; the base image is at the bottom, the other on top blended with its
opacity, or in the alternate squares of a checkerboard fixed in mm
(``core.registration.coregistration``). The view's colour map applies to the composite. The composite is
painted over the view's own image (the first layer, under the label fill and the contours)
and kept per view until the slice or a display setting changes, so repaints for contours or
points reuse it.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QRectF
from PySide6.QtGui import QImage, QPainter

from app.model.second_image import SecondImage
from core.geometry.planes import window_to_uint8
from core.registration.coregistration import blend, checkerboard_mask


class SecondImageLayer:
    """``paint(view, painter)``: the composite of the two images on the view's slice."""

    def __init__(self, second: SecondImage):
        self.second = second
        self._cache: dict[str, tuple[tuple, QImage]] = {}
        second.events.loaded.connect(self._cache.clear)

    def _key(self, view) -> tuple:
        return (view.frame_name, round(float(view._slice.depth), 6), view._slice.data.shape,
                id(view._slice), id(view.colormap), self.display_key())

    def composite(self, view) -> np.ndarray | None:
        """(H, W) uint8 composite on the view's current slice (None without a second image)."""
        return None if view._slice is None else self.composite_slice(view.frame, view._slice)

    def composite_slice(self, frame, first_slice) -> np.ndarray | None:
        """The composite on a slice of the first image (``core.geometry.planes.SliceImage`` on
        ``frame``), e.g. the 3D view's planes; None without a second image."""
        s = self.second
        if s.sampler is None:
            return None
        first = window_to_uint8(first_slice.data, *s.window_of("first"))
        other = s.sampler.sample(frame, first_slice.depth)
        if other.data.shape != first.shape:          # not on the first image's grid
            return None
        second = window_to_uint8(other.data, *s.window_of("second"))
        bottom, top = (first, second) if s.base == "first" else (second, first)
        if s.mode == "checkerboard":
            return np.where(checkerboard_mask(first_slice, s.checker_mm), bottom, top)
        return blend(bottom, top, s.opacity)

    def display_key(self) -> tuple:
        """Changes whenever the composite of a given slice would."""
        s = self.second
        return (s.window_of("first"), s.window_of("second"), s.mode, s.opacity, s.checker_mm,
                s.base, id(s.sampler))

    def image(self, view) -> QImage | None:
        key = self._key(view) if view._slice is not None else None
        cached = self._cache.get(view.frame_name)
        if cached is not None and cached[0] == key:
            return cached[1]
        grey = self.composite(view)
        if grey is None:
            return None
        grey = np.ascontiguousarray(grey)
        h, w = grey.shape
        if view.colormap is not None:
            rgb = np.ascontiguousarray(view.colormap[grey])
            image = QImage(rgb.data, w, h, 3 * w, QImage.Format.Format_RGB888)
        else:
            image = QImage(grey.data, w, h, w, QImage.Format.Format_Grayscale8)
        image = image.convertToFormat(QImage.Format.Format_RGB32)   # owns its pixels
        self._cache[view.frame_name] = (key, image)
        return image

    def paint(self, view, painter: QPainter) -> None:
        image = self.image(view)
        if image is None:
            return
        left, right, top, bottom = view._slice.extent()
        (x0, y0), (x1, y1) = view.plane_to_screen(np.array([[left, top], [right, bottom]]))
        painter.drawImage(QRectF(x0, y0, x1 - x0, y1 - y0), image)
