"""What a slice view paints over its image: crosshair, contours, points and text.

Functions of the :class:`app.views.slice_view.SliceView` they paint on (``view``), in its
screen space (``view.world_to_screen`` / ``view.plane_to_screen``): the crosshair, every
structure's cross-section (the active one last, the others dimmed), the contour points of
this slice (strokes drawn as separate polylines; points one slice away faint), and the
labels (orientation letters, slice title, window/level) with a dark outline so they read
over bright and dark image regions.
"""

from __future__ import annotations

import numpy as np
from PySide6.QtCore import QLineF, QPointF, QRect, QRectF, Qt
from PySide6.QtGui import QColor, QFont, QFontMetricsF, QImage, QPainter, QPen

CONTOUR_COLOR = QColor(255, 170, 0)          # model cross-section (orange: the first structure)
INACTIVE_ALPHA = 120                         # other structures' contours are dimmed
POINT_COLOR = QColor(0, 230, 255)            # contour points on this slice (cyan)
POINT_NEAR_COLOR = QColor(0, 230, 255, 90)   # points one slice away
CROSSHAIR_COLOR = QColor(60, 200, 60, 150)
LABEL_COLOR = QColor(255, 255, 120)
VIEW_COLORS = {"axial": QColor(220, 60, 60), "coronal": QColor(60, 170, 60),
               "sagittal": QColor(230, 200, 40)}


def paint_crosshair(view, painter: QPainter) -> None:
    """Two 1-pixel lines with a gap at the crosshair, as filled rectangles: a translucent
    pen's full-width lines cost ~1 ms per paint in the raster engine, rectangles ~0.05 ms."""
    x, y = (int(np.floor(c)) for c in view.world_to_screen(view.state.crosshair))
    w, h, gap = view.width(), view.height(), 8
    for rect in (QRect(0, y, x - gap, 1), QRect(x + gap, y, w - x - gap, 1),
                 QRect(x, 0, 1, y - gap), QRect(x, y + gap, 1, h - y - gap)):
        if rect.width() > 0 and rect.height() > 0:
            painter.fillRect(rect, CROSSHAIR_COLOR)


def paint_contours(view, painter: QPainter) -> None:
    """Every visible structure in its colour; the active one last, the others dimmed."""
    active = view.state.active
    for s in sorted(view.state.structures, key=lambda s: s is active):
        if not view.show_outline:
            break
        segments = view._segments.get(s.id)
        if segments is None or not s.visible:
            continue
        color = QColor(*s.color)
        if s is not active:
            color.setAlpha(INACTIVE_ALPHA)
        xy = view.plane_to_screen(segments).reshape(-1, 4)
        painter.setPen(QPen(color, 1.6 if s is active else 1.2))
        painter.drawLines([QLineF(a, b, c, d) for a, b, c, d in xy.tolist()])


def paint_points(view, painter: QPainter) -> None:
    step = view._step()
    active = view.state.active
    for s in view.state.structures:            # other structures' points: small, dimmed
        if s is active or not s.visible or len(s.points) == 0:
            continue
        here = s.points.on_slice(view.frame_index, view.depth, step / 2)
        if here.any():
            color = QColor(*s.color)
            color.setAlpha(INACTIVE_ALPHA)
            painter.setPen(Qt.PenStyle.NoPen)
            painter.setBrush(color)
            for x, y in view.world_to_screen(s.points.xyz[here]):
                painter.drawEllipse(QPointF(x, y), 2.5, 2.5)
    pts = active.points
    if len(pts) == 0 or not active.visible:
        painter.setBrush(Qt.BrushStyle.NoBrush)
        return
    depth_gap = np.abs(pts.depth - view.depth)
    same = pts.frame == view.frame_index
    here = same & (depth_gap <= step / 2)
    near = ~here & (np.abs(view.frame.depth(pts.xyz) - view.depth) <= 1.5 * step)
    xy = view.world_to_screen(pts.xyz)
    painter.setPen(Qt.PenStyle.NoPen)
    painter.setBrush(POINT_NEAR_COLOR)
    for x, y in xy[near]:
        painter.drawEllipse(QPointF(x, y), 3, 3)
    if here.any():
        idx = np.flatnonzero(here)
        painter.setPen(QPen(POINT_COLOR, 1))
        for stroke in np.unique(pts.stroke[idx]):     # strokes are not joined to each other
            line = idx[pts.stroke[idx] == stroke]
            painter.drawPolyline([QPointF(x, y) for x, y in xy[line]])
        painter.setPen(QPen(QColor(0, 0, 0), 1))
        painter.setBrush(POINT_COLOR)
        for x, y in xy[idx]:
            painter.drawEllipse(QPointF(x, y), 3.5, 3.5)
    painter.setBrush(Qt.BrushStyle.NoBrush)


def outlined_text(painter: QPainter, rect: QRectF, flags, text: str, color: QColor) -> None:
    """Text with a dark outline, readable over bright and dark image regions."""
    painter.setPen(QColor(0, 0, 0, 200))
    for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        painter.drawText(rect.translated(dx, dy), flags, text)
    painter.setPen(color)
    painter.drawText(rect, flags, text)


_SPRITES: dict[tuple, QImage] = {}     # outlined label texts, rendered once
_SPRITE_PAD = 3


BACKDROP_COLOR = QColor(0, 0, 0, 170)    # behind the slice title and W/L: bright slices
BACKDROPPED = ("title", "window")        # the read-outs (the letters are big and bold)


def _sprite(text: str, color: QColor, font: QFont, width: float, height: float,
            ratio: float, backdrop: bool = False) -> QImage:
    """The outlined text as a transparent image (five text draws once, then one blit); with
    ``backdrop``, on a dark translucent box that keeps it readable over white."""
    key = (text, color.rgba(), font.key(), round(width, 2), round(height, 2), ratio, backdrop)
    image = _SPRITES.get(key)
    if image is None:
        if len(_SPRITES) > 512:
            _SPRITES.clear()
        pad = _SPRITE_PAD
        w, h = width + 2 * pad, height + 2 * pad
        image = QImage(max(1, int(np.ceil(w * ratio))), max(1, int(np.ceil(h * ratio))),
                       QImage.Format.Format_ARGB32_Premultiplied)
        image.setDevicePixelRatio(ratio)
        image.fill(0)
        p = QPainter(image)
        if backdrop:
            p.setRenderHint(QPainter.RenderHint.Antialiasing)
            p.setPen(Qt.PenStyle.NoPen)
            p.setBrush(BACKDROP_COLOR)
            p.drawRoundedRect(QRectF(0, 0, w, h), 3, 3)
        p.setFont(font)
        outlined_text(p, QRectF(pad, pad, width, height), Qt.AlignmentFlag.AlignCenter, text,
                      color)
        p.end()
        _SPRITES[key] = image
    return image


def paint_labels(view, painter: QPainter) -> None:
    ratio = float(view.devicePixelRatioF())
    for name, (rect, text, color, font) in view.label_layout().items():
        rect = rect.adjusted(-2, 0, 2, 0)
        image = _sprite(text, color, font, rect.width(), rect.height(), ratio,
                        name in BACKDROPPED)
        painter.drawImage(QPointF(rect.left() - _SPRITE_PAD, rect.top() - _SPRITE_PAD), image)
    if view.hasFocus():
        w, h = view.width(), view.height()
        painter.setPen(QPen(VIEW_COLORS[view.frame_name], 2))
        painter.drawRect(QRectF(1, 1, w - 2, h - 2))


def _label_fonts(view) -> tuple[QFont, QFont]:
    letters = QFont(view.font())
    letters.setPointSize(13)
    letters.setBold(True)
    small = QFont(view.font())
    small.setPointSize(9)
    return letters, small


def label_layout(view) -> dict[str, tuple[QRectF, str, QColor, QFont]]:
    """Where each overlay text goes: name -> (tight rectangle, text, colour, font).

    The orientation letters sit at the middle of each edge, the slice title top left and
    window/level bottom right; when the title reaches the top letter (narrow views, e.g.
    an 800x600 window) the letter moves below the title instead of under it.
    """
    labels = view.frame.edge_labels()
    if not view.state.orientation_known:         # never show R/L as if they were known
        labels = {edge: "?" for edge in labels}
    letters, small = _label_fonts(view)
    big, little = QFontMetricsF(letters), QFontMetricsF(small)
    w, h, m = view.width(), view.height(), 6
    axis = "xyz"[int(np.argmax(np.abs(view.frame.n)))]
    lo, hi = view._depth_range
    index = int(round((view.depth - lo) / view._step())) + 1
    total = int(round((hi - lo) / view._step())) + 1
    title = f"{view.frame_name.capitalize()}  {axis} = {view.depth:.1f} mm  ({index}/{total})"
    if not view.state.orientation_known:
        title += "  orientation unknown"
    wl = f"W {view.state.window:.0f}  L {view.state.level:.0f}"

    def box(text, metrics, x, y, anchor_x="left", anchor_y="top"):
        tw, th = metrics.horizontalAdvance(text), metrics.height()
        x = {"left": x, "center": x - tw / 2, "right": x - tw}[anchor_x]
        y = {"top": y, "center": y - th / 2, "bottom": y - th}[anchor_y]
        return QRectF(x, y, tw, th)

    out = {"title": (box(title, little, m, m), title, VIEW_COLORS[view.frame_name], small),
           "window": (box(wl, little, w - m, h - m, "right", "bottom"), wl,
                      QColor(170, 170, 170), small)}
    top = box(labels["top"], big, w / 2, m, "center")
    if top.intersects(out["title"][0].adjusted(-4, 0, 4, 0)):
        top.moveTop(out["title"][0].bottom() + 2)
    out["top"] = (top, labels["top"], LABEL_COLOR, letters)
    out["bottom"] = (box(labels["bottom"], big, w / 2, h - m, "center", "bottom"),
                     labels["bottom"], LABEL_COLOR, letters)
    out["left"] = (box(labels["left"], big, m, h / 2, "left", "center"), labels["left"],
                   LABEL_COLOR, letters)
    out["right"] = (box(labels["right"], big, w - m, h / 2, "right", "center"),
                    labels["right"], LABEL_COLOR, letters)
    return out
