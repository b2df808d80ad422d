"""Automatic placement of library models on a patient image, through its template.

Every library model lives in a template space (``info.structure.template_space``; the demo
models in the MNI ICBM152 2009a template bundled in ``resources/``): its ``world_transform``
places it on that template. To place it on a patient image, the image is registered to the
template once (``core.registration.volumes``: affine, Mattes mutual information, multi-resolution),
giving T: image world -> template world; every model is then placed with

    placement = T^-1 @ model.world_transform        (model frame -> image world)

which becomes the start of the fit and the centre of its pose prior (``fit_points``'
``placement``), as the user's *Place here* does by hand.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.models.shape_model import ShapeModel
from core.runtime.progress import ProgressCallback


def register_to_template(image, template=None, *, transform: str = "affine",
                         progress: ProgressCallback | None = None, **kwargs):
    """Register ``image`` (a ``core.io.Volume``) to the models' template.

    ``template``: a Volume, a path, or None for the bundled MNI T1. Returns the
    ``core.registration.volumes.RegistrationResult`` whose ``transform`` maps image world -> template
    world (RAS, column vectors).
    """
    from core.io import load_volume
    from core.registration.volumes import default_template_path, register_volumes

    if template is None or isinstance(template, (str, Path)):
        template = load_volume(template or default_template_path())
    return register_volumes(image, template, transform, progress=progress, **kwargs)


def placement_through(model: ShapeModel, image_to_template: np.ndarray) -> np.ndarray:
    """The model's placement on the image: inv(T) @ model.world_transform (4x4)."""
    t = np.asarray(image_to_template, dtype=np.float64)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)) or abs(np.linalg.det(t[:3, :3])) < 1e-9:
        raise ValueError("the image-to-template transform must be a finite, invertible 4x4 matrix")
    return np.linalg.inv(t) @ model.world_transform


def nudged(image_to_template: np.ndarray, rotation: np.ndarray, translation: np.ndarray,
           centre: np.ndarray) -> np.ndarray:
    """The registration moved by hand: structures placed through the result turn by the
    rotation vector ``rotation`` (axis * angle, radians) about ``centre`` and then shift by
    ``translation`` (image world, mm). With N that rigid map, inv(T') = N @ inv(T), so
    ``placement_through(model, T') = N @ placement_through(model, T)``; returns T'."""
    from core.geometry.toolkit import rodrigues

    rot = rodrigues(np.asarray(rotation, dtype=np.float64))
    centre = np.asarray(centre, dtype=np.float64)
    move = np.eye(4)
    move[:3, :3] = rot
    move[:3, 3] = centre - rot @ centre + np.asarray(translation, dtype=np.float64)
    return np.asarray(image_to_template, dtype=np.float64) @ np.linalg.inv(move)


def nudge_of(image_to_template: np.ndarray, nudged_transform: np.ndarray,
             centre: np.ndarray) -> tuple[float, float]:
    """How far a nudged registration (:func:`nudged`) moved the structures from the
    registration's result: (shift of ``centre`` in mm, turn in degrees). The hand move in
    image world is N = inv(T') @ T."""
    from core.geometry.toolkit import rotation_vector

    move = np.linalg.inv(np.asarray(nudged_transform, dtype=np.float64)) \
        @ np.asarray(image_to_template, dtype=np.float64)
    centre = np.asarray(centre, dtype=np.float64)
    angle = float(np.degrees(np.linalg.norm(rotation_vector(move[:3, :3]))))
    shift = float(np.linalg.norm(move[:3, :3] @ centre + move[:3, 3] - centre))
    return shift, angle
