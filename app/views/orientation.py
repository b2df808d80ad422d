"""A labelled orientation cube for the 3D view (as 3D Slicer's and ITK-SNAP's).

World coordinates are RAS: the cube's faces read R/L (+x/-x), A/P (+y/-y) and S/I (+z/-z),
so the viewer sees at a glance from which side the structure is shown. Drawn by VTK's
``vtkAnnotatedCubeActor`` in a corner viewport that turns with the camera
(``Plotter.add_orientation_widget``).
"""

from __future__ import annotations

FACES = {"XPlus": "R", "XMinus": "L", "YPlus": "A", "YMinus": "P", "ZPlus": "S", "ZMinus": "I"}


def add_orientation_cube(plotter):
    """Add the RAS-labelled cube to ``plotter`` (bottom left); returns the widget."""
    from vtkmodules.vtkRenderingAnnotation import vtkAnnotatedCubeActor

    cube = vtkAnnotatedCubeActor()
    for face, text in FACES.items():
        getattr(cube, f"Set{face}FaceText")(text)
    cube.SetFaceTextScale(0.65)
    cube.GetCubeProperty().SetColor(0.82, 0.84, 0.9)
    for face, colour in (("X", (0.85, 0.25, 0.25)), ("Y", (0.25, 0.7, 0.3)),
                         ("Z", (0.3, 0.45, 0.9))):
        for side in ("Plus", "Minus"):
            getattr(cube, f"Get{face}{side}FaceProperty")().SetColor(*colour)
    cube.GetTextEdgesProperty().SetColor(0.2, 0.2, 0.2)
    return plotter.add_orientation_widget(cube, viewport=(0.0, 0.0, 0.2, 0.2))
