"""The Segment tab's tools (issue 17) installed on the main window, each by its own module.

Every tool adds its actions, side-panel box, view layers and session hooks itself, so the
window does not know their details; the order matters only for where boxes and menu
entries land.
"""

from __future__ import annotations


def install_segment_tools(window) -> None:
    """Compose the features (``window.features[name]``): label map and hand edits
    (``"editing"``), ``"navigation"``, ``"placement-nudge"``, ruler and angle
    (``"measurements"``), ``"second-image"``, ``"demo-tour"``."""
    from app.demo_tour import DemoTourFeature  # Help > Demo tour
    from app.panels.editing import Editing  # label map, brush, move model
    from app.panels.measurements import MeasurementTools  # ruler and angle
    from app.panels.navigation import Navigation  # zoom, layouts, colour maps...
    from app.panels.placement_nudge import PlacementNudge  # adjust automatic placement
    from app.panels.second_image import SecondImageFeature  # T2/FLAIR/CT over the T1

    window.add_feature("editing", Editing(window))
    window.add_feature("navigation", Navigation(window))
    window.add_feature("placement-nudge", PlacementNudge(window))
    window.add_feature("measurements", MeasurementTools(window))
    window.add_feature("second-image", SecondImageFeature(window))
    window.add_feature("demo-tour", DemoTourFeature(window))
