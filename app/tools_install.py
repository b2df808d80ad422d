"""The Segment tab's tools (issue 17) installed on the main window, each by its own module.

Every tool adds its actions, side-panel box, view layers and session hooks itself, so the
window does not know their details; the order matters only for where boxes and menu
entries land.
"""

from __future__ import annotations


def install_segment_tools(window) -> None:
    """Label map and hand edits (``window.labels``), navigation, ruler and angle
    (``window.measurements``), the second image (``window.second_image``), the demo tour."""
    from app.demo_tour import install_demo_tour            # Help > Demo tour
    from app.panels.editing import install_editing         # label map, brush, move model
    from app.panels.measurements import install_measurements   # ruler and angle
    from app.panels.navigation import Navigation   # zoom, layouts, colour maps...
    from app.panels.placement_nudge import install_nudge   # adjust automatic placement
    from app.panels.second_image import install_second_image   # T2/FLAIR/CT over the T1

    window.labels = install_editing(window)
    window.add_feature("navigation", Navigation(window))
    install_nudge(window)
    window.measurements = install_measurements(window)
    window.second_image = install_second_image(window)
    install_demo_tour(window)
