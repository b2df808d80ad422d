"""The model library: which structure a model file describes, and where model files are found.

A model file (``core.io.save_model``) carries a description of its structure in its header,
under ``info["structure"]``::

    {"name": "caudate nucleus", "side": "left", "color": [0.20, 0.63, 0.17],
     "template_space": "MNI152NLin2009aSym", "demo": true,
     "target": [x, y, z],            # optional default target, model frame mm
     "target_name": "dorsolateral (motor) STN",   # optional: what the target is
     "source_space": "MNI152NLin2009cAsym"}       # optional: the atlas's own space

``side`` is ``"left"``, ``"right"`` or ``"midline"`` (or empty when unknown); ``color`` is RGB
in 0..1 (as 3D Slicer's segment colours); ``template_space`` names the image space the model's
``world_transform`` places it in (the models' template image for automatic placement);
``demo`` marks models built from synthetic populations, which are shown as such. ``target``
is a point of the model frame: it is anchored to the mean shape's vertices
(``core.planning.frames.anchored_point_weights``) and carried to the fitted shape, so the target
moves with the fit; ``source_space`` names the space of the atlas a model was derived from
when it differs from ``template_space`` (the CIT168 models: derived in MNI152NLin2009cAsym,
placed on the 2009a template by a measured translation, ``info.atlas``). Files
written before this description existed still open: their structure is derived from the file
name.

The library is every ``*.npz`` / ``*.h5`` model in ``resources/models/`` (shipped) and in the
user's model folder: ``$SSM_STUDIO_DATA_DIR/models`` if set, else the platform's per-user data
location (``$XDG_DATA_HOME`` or ``~/.local/share`` on Linux, ``~/Library/Application Support``
on macOS, ``%APPDATA%`` on Windows) + ``ssm-studio/models``.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import platformdirs

from core import RESOURCES_DIR
from core.models.shape_model import ShapeModel

RESOURCES_MODELS = RESOURCES_DIR / "models"
MNI_TEMPLATE_SPACE = "MNI152NLin2009aSym"
SIDES = ("left", "right", "midline", "")
MODEL_SUFFIXES = (".npz", ".h5")

#: Default colours (RGB 0..1) by structure, as in FreeSurfer's colour table where it has one.
DEFAULT_COLORS = {
    "caudate": (0.48, 0.73, 0.86),
    "putamen": (0.93, 0.05, 0.69),
    "pallidum": (0.05, 0.19, 1.0),
    "thalamus": (0.0, 0.46, 0.05),
    "subthalamic": (0.93, 0.68, 0.05),
    "pallidus internus": (0.05, 0.19, 1.0),
    "pallidus externus": (0.37, 0.55, 1.0),
    "red nucleus": (0.86, 0.08, 0.24),
    "nigra": (0.36, 0.24, 0.55),
}
FALLBACK_COLOR = (0.95, 0.65, 0.10)


@dataclass(frozen=True)
class StructureInfo:
    """What a model describes: structure name, side, colour, template space, demo flag."""

    name: str
    side: str = ""
    color: tuple[float, float, float] = FALLBACK_COLOR
    template_space: str = ""
    demo: bool = False
    target: tuple[float, float, float] | None = None
    target_name: str = ""
    source_space: str = ""

    def __post_init__(self) -> None:
        if self.side not in SIDES:
            raise ValueError(f"structure side must be one of left/right/midline, got {self.side!r}")
        color = tuple(float(c) for c in self.color)
        if len(color) != 3 or not all(0.0 <= c <= 1.0 for c in color):
            raise ValueError(f"structure colour must be three numbers in 0..1, got {self.color!r}")
        object.__setattr__(self, "color", color)
        if self.target is not None:
            target = tuple(float(c) for c in self.target)
            if len(target) != 3:
                raise ValueError(f"structure target must be three coordinates, got {self.target!r}")
            object.__setattr__(self, "target", target)

    @property
    def label(self) -> str:
        """Human-readable name: 'Left caudate nucleus (demo)'."""
        text = f"{self.side} {self.name}".strip() if self.side in ("left", "right") else self.name
        text = text[:1].upper() + text[1:]
        return f"{text} (demo)" if self.demo else text

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["color"] = list(self.color)
        if self.target is None:
            out.pop("target")
        else:
            out["target"] = list(self.target)
        for key in ("target_name", "source_space"):  # absent when empty: older headers as they were
            if not out[key]:
                out.pop(key)
        return out

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> StructureInfo:
        if not isinstance(doc, dict) or not isinstance(doc.get("name"), str):
            raise ValueError("structure description must be an object with a 'name'")
        return cls(name=doc["name"], side=str(doc.get("side", "")),
                   color=tuple(doc.get("color", default_color(doc["name"]))),
                   template_space=str(doc.get("template_space", "")),
                   demo=bool(doc.get("demo", False)), target=doc.get("target"),
                   target_name=str(doc.get("target_name", "")),
                   source_space=str(doc.get("source_space", "")))


def default_color(name: str) -> tuple[float, float, float]:
    """The conventional colour of a structure, by a word in its name."""
    lowered = name.lower()
    for word, color in DEFAULT_COLORS.items():
        if word in lowered:
            return color
    return FALLBACK_COLOR


def structure_from_name(text: str) -> StructureInfo:
    """The structure a free-text name means ('left_caudate', 'caudate nucleus (left)')."""
    return _from_name(text.replace("(", " ").replace(")", " "))


def _from_name(text: str) -> StructureInfo:
    """Structure guessed from a file or structure name ('left_caudate', 'Right-Thalamus')."""
    words = text.replace("_", " ").replace("-", " ").split()
    side = ""
    for w in list(words):
        if w.lower() in ("left", "lh", "l"):
            side = "left"
            words.remove(w)
        elif w.lower() in ("right", "rh", "r"):
            side = "right"
            words.remove(w)
    name = " ".join(words).strip() or "structure"
    return StructureInfo(name=name, side=side, color=default_color(name))


def structure_info(model: ShapeModel, path: str | os.PathLike | None = None) -> StructureInfo:
    """The model's structure description; derived from older headers or the file name."""
    doc = model.info.get("structure")
    if isinstance(doc, dict):
        try:
            return StructureInfo.from_dict(doc)
        except (TypeError, ValueError):
            pass
    if isinstance(doc, str) and doc:  # round-1 demo files: a plain name ("left caudate nucleus")
        return _from_name(doc)
    if path is not None:
        return _from_name(Path(path).name.split(".")[0])
    return StructureInfo(name="structure")


def with_structure(model: ShapeModel, info: StructureInfo) -> ShapeModel:
    """Attach ``info`` to the model's header (in place; returns the model)."""
    model.info["structure"] = info.to_dict()
    return model


def user_models_dir() -> Path:
    """The per-user model folder (not created here): ``$SSM_STUDIO_DATA_DIR/models``, else
    :func:`platformdirs.user_data_dir` (roaming on Windows, as before) + ``ssm-studio/models``."""
    override = os.environ.get("SSM_STUDIO_DATA_DIR")
    if override:
        return Path(override) / "models"
    return Path(platformdirs.user_data_dir("ssm-studio", appauthor=False, roaming=True)) / "models"


def library_dirs() -> list[Path]:
    """Folders searched for library models: the shipped one first, then the user's."""
    return [RESOURCES_MODELS, user_models_dir()]


@dataclass(frozen=True)
class LibraryEntry:
    """One model of the library (or one that could not be read, with ``error``)."""

    path: Path
    structure: StructureInfo | None = None
    n_vertices: int = 0
    n_factors: int = 0
    error: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


def list_library(dirs: list[Path] | None = None) -> list[LibraryEntry]:
    """Every model file in the library folders, sorted by structure label then path.

    A file that cannot be read is listed with its one-line error, so the GUI can show it.
    """
    from core.io import load_model

    entries: list[LibraryEntry] = []
    for folder in dirs if dirs is not None else library_dirs():
        if not folder.is_dir():
            continue
        for path in sorted(folder.iterdir()):
            if path.name.startswith(".") or path.suffix.lower() not in MODEL_SUFFIXES:
                continue
            try:
                model = load_model(path)
            except (ValueError, OSError) as exc:
                entries.append(LibraryEntry(path, error=str(exc)))
                continue
            entries.append(LibraryEntry(path, structure_info(model, path), model.n_vertices,
                                        model.n_factors))
    return sorted(entries, key=lambda e: (e.structure is None,
                                          e.structure.label if e.structure else "", str(e.path)))
