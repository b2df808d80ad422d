"""Contour points on a slice view: adding one under the cursor, finding and deleting one.

Functions of the :class:`app.views.slice_view.SliceView` they act on (``view``); a point is
added at the world position under the pixel, on the view's slice, to the active structure
(refused with a message when it is locked or hidden, or outside the image).
"""

from __future__ import annotations

import numpy as np


def add_point_at(view, x: float, y: float, checkpoint: bool = True,
                 stroke: str = "click") -> np.ndarray | None:
    """Add a contour point on this slice under widget pixel (x, y); returns it (world)."""
    world = view.screen_to_world(x, y)
    active = view.state.active
    if active.locked or not active.visible:
        view.message.emit(f"{active.label} is {'locked' if active.locked else 'hidden'}: "
                          "unlock or show it in the structure list to draw")
        return None
    if view.state.volume is not None:
        lo, hi = view.state.volume.world_bounds()
        if np.any(world < lo - 1e-6) or np.any(world > hi + 1e-6):
            view.message.emit("Point outside the image: not added")
            return None
    view.state.active.add_point(world, view.frame_name, view.depth, checkpoint=checkpoint, stroke=stroke)
    return world


def points_here(view) -> np.ndarray:
    """Indices of the active structure's points drawn on this view's slice, in order."""
    return np.flatnonzero(view.state.active.points.on_slice(view.frame_index, view.depth,
                                                     view._step() / 2))


def point_near(view, x: float, y: float, radius_px: float = 8.0) -> int | None:
    """Index of the contour point on this slice nearest to pixel (x, y), within the radius."""
    pts = view.state.active.points
    if len(pts) == 0:
        return None
    here = np.flatnonzero(pts.on_slice(view.frame_index, view.depth, view._step() / 2))
    if here.size == 0:
        return None
    d = np.hypot(*(view.world_to_screen(pts.xyz[here]) - [x, y]).T)
    best = int(np.argmin(d))
    return int(here[best]) if d[best] <= radius_px else None


def delete_point_near(view, x: float, y: float) -> bool:
    index = view.point_near(x, y)
    if index is None or view.state.active.locked:
        return False
    view.state.active.remove_point(index)
    return True
