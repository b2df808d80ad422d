"""What the model builder knows, apart from widgets: plain Python, no Qt (testable headless).

The training-mesh entries, the staged build (:class:`core.build.stages.StagedBuild` with its stage
cache), the model shown and whether it is saved, and the last evaluation. The panel's widgets
read and change it; nothing here draws or asks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from app.panels.builder_engine import MeshEntry
from core.build.stages import StageCache, StagedBuild, aligned_meshes, corresponded_meshes

MeshTriples = list[tuple[str, Any, Any]]  # (name, vertices (N, 3), faces (F, 3))


@dataclass
class BuilderState:
    """The builder's data: entries, stages, model, saved file, evaluation."""

    entries: list[MeshEntry] = field(default_factory=list)
    build: StagedBuild = field(default_factory=StagedBuild)
    model: Any = None  # core.models.shape_model.ShapeModel
    model_key: tuple | None = None  # the model stage's key when it was built here
    saved_path: str | None = None
    saved_key: int | None = None  # id() of the model the saved file holds
    evaluation: dict[str, Any] = field(default_factory=dict)

    @property
    def stages(self) -> StageCache:
        """The completed stages (``stages["model"].result`` is the last model built)."""
        return self.build.cache

    def usable_entries(self) -> list[MeshEntry]:
        return [e for e in self.entries if e.mesh is not None and e.included]

    def correspondence_report(self) -> tuple[dict[str, float], dict[str, str]]:
        """Residual (mm) and failure reason by mesh name from the cached correspondence."""
        if "correspondence" not in self.stages:
            return {}, {}
        corr = self.stages["correspondence"].result
        fits = {m.name: r for m, r in zip(corr.meshes, corr.residuals_mm)
                if m is not None and r is not None}
        return fits, dict(corr.failures)

    def grooming_report(self) -> dict[str, str]:
        """What grooming repaired or dropped, one line by mesh name, from the cached
        correspondence (:func:`core.correspondence.grooming.describe`)."""
        if "correspondence" not in self.stages:
            return {}
        from core.correspondence.grooming import describe

        grooming = getattr(self.stages["correspondence"].result, "grooming", None) or {}
        return {name: describe(rep) for name, rep in grooming.items()}

    def safeguard_report(self) -> list[str]:
        """What the correspondence safeguard tried and kept, one line a judged stage, from the
        cached correspondence (:func:`core.correspondence.safeguard.describe`)."""
        if "correspondence" not in self.stages:
            return []
        from core.correspondence.safeguard import describe

        return describe(getattr(self.stages["correspondence"].result, "safeguard", None) or {})

    def meshes_for(self, which: str) -> MeshTriples:
        """The training shapes "as loaded", "corresponded" or "aligned" (empty if not built)."""
        if which == "as loaded":
            return [(e.name, e.mesh.vertices, e.mesh.faces) for e in self.usable_entries()]
        if "correspondence" not in self.stages:
            return []
        corr = self.stages["correspondence"].result
        if which == "corresponded":
            return corresponded_meshes(corr)
        if which == "aligned" and "alignment" in self.stages:
            return aligned_meshes(corr, self.stages["alignment"].result)
        return []

    def model_is_current(self) -> bool:
        """Whether the model shown is the cached model stage's result."""
        return self.model is not None and self.model_key is not None and \
            "model" in self.stages and self.stages["model"].key == self.model_key

    def record_evaluation(self, results: dict[str, Any], same_params: bool) -> None:
        """Keep ``results``; the shown model's own method's row goes into its metadata when it
        was evaluated with the parameters it was built with (``same_params``)."""
        from core.evaluation import summary_rows

        self.evaluation = results
        if self.model_is_current() and self.model.method in results and same_params:
            self.model.info["evaluation"] = summary_rows(
                {self.model.method: results[self.model.method]})[0]
            self.saved_key = None  # the file on disk lacks the evaluation

    @property
    def is_saved(self) -> bool:
        return self.saved_path is not None and self.saved_key == id(self.model)

    def save_model(self, path: str | Path) -> str:
        """Save the model to ``path`` (atomic); returns the path written."""
        from core.io import save_model

        if self.model is None:
            raise ValueError("no model to save: build one first")
        save_model(str(path), self.model)
        self.saved_path, self.saved_key = str(path), id(self.model)
        return str(path)

    def open_model(self, path: str | Path):
        """Load a model file as the shown model (not a build result); returns it."""
        from core.io import load_model

        model = load_model(path)
        self.model, self.model_key = model, None
        self.saved_path, self.saved_key = str(path), id(model)
        return model
