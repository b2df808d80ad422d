"""The model build as cached stages: rerun only the stages whose inputs changed.

The build ``correspondence -> alignment -> model`` (``core.build.pipeline``'s stage functions) is
memoised stage by stage, as scikit-learn's ``Pipeline(memory=...)`` caches its fitted
transformers: each completed stage is stored with the *key* of everything it was computed from
(the training meshes and its own parameters, plus the key of the stage before it). A later build
compares the keys of the current settings with the stored ones and plans only the stale stages:
changing the model's parameters refits the model and reuses the correspondence and the
alignment; changing the alignment reruns alignment and model. A stage stored under a new key
drops the later stages computed from an older one, so the cache never mixes inputs.

No Qt here: :class:`StagedBuild` is the headless "Logic" (cf. 3D Slicer's Logic/Widget split)
behind the GUI's model builder, which runs each :meth:`StagedBuild.job` in a worker thread and
:meth:`StagedBuild.store` s its result on the GUI thread.

Usage::

    build = StagedBuild()
    settings = BuildSettings(meshes, reference="auto", method="pca")
    for stage in build.plan(settings):
        result = build.job(stage, settings)(progress=None)     # in a worker, cancellable
        build.store(stage, settings, result, seconds=...)
    model = build.cache["model"].result                         # a core.models.shape_model.ShapeModel
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Hashable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from core.io import TriMesh
from core.runtime.progress import ProgressCallback, report, sub_progress

__all__ = ["STAGES", "NO_CORRESPONDENCE", "DEFAULT_N_REFERENCES", "BuildSettings", "CachedStage", "StageCache",
           "StagedBuild", "run_correspondence", "run_alignment", "run_model", "run_evaluation",
           "corresponded_meshes", "aligned_meshes"]

STAGES = ("correspondence", "alignment", "model")
# The reference choice for training meshes that already share one topology.
NO_CORRESPONDENCE = "none (already corresponded)"
# core.correspondence.establish_correspondence's default n_references, without importing it
# (the engine pulls in scipy.optimize: ~1.8 s; tests/test_stages.py keeps them equal).
DEFAULT_N_REFERENCES = 1


def _frozen(params: Mapping[str, Any]) -> tuple:
    """A hashable, order-free stand-in for a parameter dict (values compared by ``repr``, so
    lists and arrays given as parameters count as equal when they print the same)."""
    return tuple(sorted((str(k), repr(v)) for k, v in params.items()))


@dataclass(frozen=True)
class BuildSettings:
    """Everything a build depends on.

    Parameters
    ----------
    meshes : sequence of TriMesh
        The training meshes, in order.
    tokens : sequence of hashable, optional
        One identity per mesh for the cache keys (e.g. ``(path, id(mesh))``); by default the
        meshes' ``id``. Two settings with equal tokens are assumed to hold the same meshes.
    reference : "auto", int or :data:`NO_CORRESPONDENCE`
        Correspondence reference: automatic choice, an index into ``meshes``, or none for
        meshes that already share one topology.
    n_references : int
        Candidate references tried with ``reference="auto"`` (ignored otherwise).
    mirror_check : bool
        Leave out inputs whose mirror image fits the others better (a left/right mix-up;
        ``establish_correspondence``'s ``mirror_check``). False for a population in which a
        chiral feature takes either sign. Ignored without correspondence.
    align_method, align_transform : str
        ``core.build.pipeline.align``'s ``method`` and ``transform``.
    method : str
        Model-building method (a ``core.models`` name).
    params : mapping
        The method's estimator parameters.
    """

    meshes: Sequence[TriMesh]
    tokens: Sequence[Hashable] | None = None
    reference: str | int = "auto"
    n_references: int = DEFAULT_N_REFERENCES
    mirror_check: bool = True
    align_method: str = "sync"
    align_transform: str = "similarity"
    method: str = "pca"
    params: Mapping[str, Any] = field(default_factory=dict)

    def keys(self) -> dict[str, tuple]:
        """The input key of each stage; a cached stage is current when its key equals this.

        Keys nest (the alignment's key holds the correspondence's, the model's the
        alignment's), so a stage's key changes whenever any earlier input changes.
        """
        tokens = tuple(self.tokens) if self.tokens is not None else \
            tuple(id(m) for m in self.meshes)
        if len(tokens) != len(self.meshes):
            msg = f"got {len(tokens)} cache tokens for {len(self.meshes)} meshes"
            raise ValueError(msg)
        n_refs = int(self.n_references) if self.reference == "auto" else 0
        # the mirror check's default leaves the key as it was before the setting existed
        mirror: tuple[str, ...] = () if self.mirror_check or self.reference == NO_CORRESPONDENCE \
            else ("no mirror check",)
        corr = (tokens, self.reference, n_refs, *mirror)
        align = (corr, self.align_method, self.align_transform)
        model = (align, self.method, _frozen(self.params))
        return {"correspondence": corr, "alignment": align, "model": model}


@dataclass
class CachedStage:
    """A completed stage: the key of its inputs, its result and how long it took (s)."""

    key: tuple
    result: Any
    seconds: float


class StageCache(Mapping[str, CachedStage]):
    """The completed stages by name (a read-only mapping; write with :meth:`store`)."""

    def __init__(self, stages: Sequence[str] = STAGES):
        self.stages = tuple(stages)
        self._done: dict[str, CachedStage] = {}

    def __getitem__(self, stage: str) -> CachedStage:
        return self._done[stage]

    def __iter__(self) -> Iterator[str]:
        return (s for s in self.stages if s in self._done)

    def __len__(self) -> int:
        return len(self._done)

    def __repr__(self) -> str:
        return f"StageCache({', '.join(self) or 'empty'})"

    def is_current(self, stage: str, keys: Mapping[str, tuple]) -> bool:
        """Whether ``stage`` is cached under the key it has in ``keys``."""
        cached = self._done.get(stage)
        return cached is not None and cached.key == keys.get(stage)

    def plan(self, keys: Mapping[str, tuple]) -> list[str]:
        """The stages to run, in order: from the first one that is not current to the end."""
        for i, stage in enumerate(self.stages):
            if not self.is_current(stage, keys):
                return list(self.stages[i:])
        return []

    def status(self, keys: Mapping[str, tuple] | None) -> dict[str, str]:
        """Per stage "not run", "done" or "out of date" (``keys`` None: settings unreadable,
        every cached stage counts as out of date)."""
        out = {}
        for stage in self.stages:
            if stage not in self._done:
                out[stage] = "not run"
            elif keys is not None and self.is_current(stage, keys):
                out[stage] = "done"
            else:
                out[stage] = "out of date"
        return out

    def store(self, stage: str, key: tuple, result: Any, seconds: float = 0.0) -> None:
        """Keep ``result`` of ``stage`` under ``key``; drop later stages built on other input.

        A later stage's key starts with the key of the stage before it, so it stays only if it
        was computed from exactly this result's inputs.
        """
        if stage not in self.stages:
            msg = f"unknown stage {stage!r}; expected one of {', '.join(self.stages)}"
            raise ValueError(msg)
        self._done[stage] = CachedStage(key, result, float(seconds))
        upstream = key
        for later in self.stages[self.stages.index(stage) + 1:]:
            cached = self._done.get(later)
            if cached is None:
                continue
            if cached.key[0] != upstream:
                del self._done[later]
            else:
                upstream = cached.key

    def clear(self) -> None:
        self._done.clear()


class StagedBuild:
    """A model build whose completed stages are reused while their inputs stay the same.

    Attributes
    ----------
    cache : StageCache
        The completed stages (``cache["model"].result`` is the last ShapeModel built).
    """

    def __init__(self) -> None:
        self.cache = StageCache()

    def plan(self, settings: BuildSettings) -> list[str]:
        """The stages a build with ``settings`` has to run, in order (empty: up to date)."""
        if len(settings.meshes) < 3:
            msg = f"a shape model needs at least 3 training meshes, got {len(settings.meshes)}"
            raise ValueError(msg)
        return self.cache.plan(settings.keys())

    def job(self, stage: str, settings: BuildSettings) -> Callable[..., Any]:
        """``stage``'s computation with its inputs bound: call it as ``job(progress=cb)``.

        The earlier stages' results are taken from the cache now, so the job does not see
        later changes of the cache (it can run in another thread).
        """
        if stage not in STAGES:
            msg = f"unknown stage {stage!r}; expected one of {', '.join(STAGES)}"
            raise ValueError(msg)
        if stage == "correspondence":
            return functools.partial(run_correspondence, list(settings.meshes),
                                     reference=settings.reference,
                                     n_references=settings.n_references,
                                     mirror_check=settings.mirror_check)
        corr = self._current("correspondence", settings)
        if stage == "alignment":
            return functools.partial(run_alignment, corr, method=settings.align_method,
                                     transform=settings.align_transform)
        aligned = self._current("alignment", settings)
        return functools.partial(run_model, corr, aligned, method=settings.method,
                                 params=dict(settings.params))

    def _current(self, stage: str, settings: BuildSettings) -> Any:
        if not self.cache.is_current(stage, settings.keys()):
            msg = f"the {stage} stage is not up to date: run it first"
            raise ValueError(msg)
        return self.cache[stage].result

    def store(self, stage: str, key: tuple, result: Any, seconds: float = 0.0) -> None:
        """Keep a finished job's result under the key it was started with; a model also gets
        the correspondence report and the stage timings in its ``info``."""
        self.cache.store(stage, key, result, seconds)
        if stage == "model":
            result.info.setdefault("timings", {}).update(
                {f"{s}_seconds": round(self.cache[s].seconds, 3) for s in STAGES if s in self.cache})
            result.info["correspondence"] = self.cache["correspondence"].result.provenance()

    def run(self, settings: BuildSettings, progress: ProgressCallback | None = None):
        """Run the stale stages in this thread; returns the ShapeModel (cached stages reused)."""
        import time

        plan = self.plan(settings)
        keys = settings.keys()
        for i, stage in enumerate(plan):
            started = time.monotonic()
            result = self.job(stage, settings)(
                progress=sub_progress(progress, i / len(plan), (i + 1) / len(plan)))
            self.store(stage, keys[stage], result, time.monotonic() - started)
        return self.cache["model"].result


# ------------------------------------------------------------------------------------------
# The stage computations (each takes plain data, reports progress, may raise Cancelled)
# ------------------------------------------------------------------------------------------


def run_correspondence(meshes: list[TriMesh], reference: str | int = "auto",
                       n_references: int = DEFAULT_N_REFERENCES, progress: ProgressCallback | None = None,
                       mirror_check: bool = True):
    """Stage 1 (``core.build.pipeline.correspond``): every mesh with the reference's topology.

    ``reference`` is "auto", an index into ``meshes``, or :data:`NO_CORRESPONDENCE` for meshes
    that already share one topology (checked; they are used as they are). ``mirror_check``:
    :class:`BuildSettings`'.
    Returns a ``core.correspondence.CorrespondenceResult``.
    """
    from core.build import pipeline
    from core.correspondence import CorrespondenceResult

    if reference == NO_CORRESPONDENCE:
        report(progress, 0.0, "checking the meshes share one topology")
        names, shapes, faces = pipeline.corresponded_shapes(meshes)
        report(progress, 1.0, "meshes already in correspondence")
        return CorrespondenceResult(
            meshes=[TriMesh(x, faces, n) for x, n in zip(shapes, names)], reference_index=None,
            reference_name="(input topology)", faces=faces, residuals_mm=[None] * len(names),
            failures={}, timings={})
    options = {} if mirror_check else {"mirror_check": False}
    return pipeline.correspond(meshes, reference=reference, n_references=n_references,
                               progress=progress, **options)


def _corresponded(corr) -> tuple[list[str], np.ndarray]:
    """Names and (K, N, 3) vertices of the meshes that were put in correspondence."""
    pairs = [(m.name, m.vertices) for m in corr.meshes if m is not None]
    if len(pairs) < 3:
        msg = (f"only {len(pairs)} meshes could be put in correspondence; a model needs at "
               "least 3")
        raise ValueError(msg)
    return [p[0] for p in pairs], np.stack([p[1] for p in pairs])


def run_alignment(corr, method: str = "sync", transform: str = "similarity",
                  progress: ProgressCallback | None = None):
    """Stage 2 (``core.build.pipeline.align``): remove the pose of the corresponded shapes."""
    from core.build import pipeline

    _, shapes = _corresponded(corr)
    return pipeline.align(shapes, method=method, transform=transform, progress=progress)


def run_model(corr, aligned, method: str = "pca", params: Mapping[str, Any] | None = None,
              progress: ProgressCallback | None = None):
    """Stage 3 (``core.build.pipeline.fit_model``): fit the model on the aligned shapes; returns a
    ShapeModel placed in world by ``core.build.pipeline.world_placement``."""
    from core.build import pipeline

    names, shapes = _corresponded(corr)
    estimator = pipeline.fit_model(aligned.aligned, corr.faces, method=method,
                                   method_params=dict(params or {}), progress=progress)
    world = pipeline.world_placement(estimator.mean_, shapes,
                                     aligned.transform if aligned.method != "none" else "rigid")
    info = {"alignment": {"method": aligned.method, "transform": aligned.transform},
            "n_iter": getattr(estimator, "n_iter_", None),
            "converged": getattr(estimator, "converged_", None)}
    # the estimator stores each factor's share of the training variance in the model's info
    # (info["explained_variance_ratio"], shown by the builder's factor list)
    return estimator.to_shape_model(corr.faces, world_transform=world, source_meshes=names,
                                    info=info)


def run_evaluation(corr, aligned, methods: Mapping[str, Mapping[str, Any]],
                   progress: ProgressCallback | None = None) -> dict[str, Any]:
    """Evaluate each method (name -> parameters) on the aligned training shapes.

    Returns ``core.evaluation.evaluate_model``'s result per method (per-shape "avg"/"max"
    errors in mm for reconstruction, generalisation, specificity, sparse reconstruction;
    compactness).
    """
    from core.evaluation import evaluate_model

    results = {}
    for i, (method, params) in enumerate(methods.items()):
        sub = sub_progress(progress, i / len(methods), (i + 1) / len(methods))
        report(sub, 0.0, f"evaluating {method}")
        results[method] = evaluate_model(method, aligned.aligned, corr.faces, params=dict(params),
                                         progress=sub)
    return results


def corresponded_meshes(corr) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(name, vertices, faces)`` of each corresponded mesh (world mm)."""
    return [(m.name, m.vertices, corr.faces) for m in corr.meshes if m is not None]


def aligned_meshes(corr, aligned) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(name, vertices, faces)`` of each aligned shape (model frame)."""
    names = [m.name for m in corr.meshes if m is not None]
    return [(n, x, corr.faces) for n, x in zip(names, aligned.aligned)]
