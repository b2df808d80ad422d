"""The live refit: each edit of a structure's points refits that structure in a worker thread.

One :class:`app.workers.LatestWinsRunner` per structure (newest edit wins, stale results are
dropped), so editing one structure never cancels another's pending fit and the others are
never refitted. A fit is warm-started from the structure's last fit when the surface still
is that fit. Its result is applied to the structure it was computed for, unless that
structure's model was replaced or it left the workspace meanwhile.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
from PySide6.QtCore import QObject, Signal

from app.model.state import FitInfo, Structure, WorkspaceState
from app.workers import LatestWinsRunner


class RefitController(QObject):
    """Schedules refits and applies their results to the workspace model.

    Signals
    -------
    applied(object)
        A ``core.reconstruction.FitResult`` was applied to its structure.
    failed(str)
        The newest fit of a structure failed (one-line message); its surface is kept.
    busy(bool)
        A fit started while none was running / no fit is running any more.
    submitted()
        A refit was submitted (its result, or a newer one's, will be applied or fail).
    """

    applied = Signal(object)
    failed = Signal(str)
    busy = Signal(bool)
    submitted = Signal()

    def __init__(self, state: WorkspaceState, settings: Callable[[], dict],
                 auto: Callable[[], bool] = lambda: True, parent: QObject | None = None):
        super().__init__(parent)
        self.state = state
        self.settings = settings           # () -> {"method", "pose", "prior_weight"}
        self.auto = auto                   # () -> refit on every edit?
        self.refit_times: list[float] = []
        self._runners: dict[int, LatestWinsRunner] = {}
        self._suspended = 0
        state.events.points.connect(self._on_points)

    def _on_points(self) -> None:
        if self._suspended:
            return
        if self.auto():
            self.schedule()
        elif self.state.active.model is not None and len(self.state.active.points):
            from dataclasses import replace

            s = self.state.active
            s.set_fit_info(replace(s.fit_info, out_of_date=True))

    def settings_changed(self) -> None:
        """Another method or prior: no warm start from the old fits; refit the active one."""
        for s in self.state.structures:
            s.last_fit = None
        if self.auto() and len(self.state.active.points):
            self.schedule()

    @contextmanager
    def suspended(self) -> Iterator[None]:
        """No automatic refit inside (restoring a session shows its stored fit)."""
        self._suspended += 1
        try:
            yield
        finally:
            self._suspended -= 1

    @property
    def is_suspended(self) -> bool:
        return bool(self._suspended)

    def runner_for(self, structure: Structure) -> LatestWinsRunner:
        runner = self._runners.get(structure.id)
        if runner is None:
            runner = LatestWinsRunner(self)
            runner.result.connect(lambda value, gen, s=structure: self._on_result(s, value))
            runner.failed.connect(lambda message, gen, s=structure: self._on_failed(s, message))
            runner.busy.connect(self._on_busy)
            self._runners[structure.id] = runner
        return runner

    @property
    def runner(self) -> LatestWinsRunner:
        """The active structure's runner."""
        return self.runner_for(self.state.active)

    @property
    def is_busy(self) -> bool:
        return any(r.is_busy for r in self._runners.values())

    def cancel(self, structure: Structure | None = None) -> None:
        """Stop the pending fit of ``structure`` (every structure's if None)."""
        runners = self._runners.values() if structure is None else \
            [r for sid, r in self._runners.items() if sid == structure.id]
        for runner in runners:
            runner.cancel()

    def wait(self, msecs: int = 30000) -> None:
        for runner in self._runners.values():
            runner.wait(msecs)

    def wait_idle(self, timeout_ms: int = 10000) -> bool:
        """Process events until no refit is pending (tests, scripts); False on timeout."""
        from PySide6.QtWidgets import QApplication

        deadline = time.perf_counter() + timeout_ms / 1000
        app = QApplication.instance()
        while self.is_busy and time.perf_counter() < deadline:
            app.processEvents()
            time.sleep(0.002)
        app.processEvents()
        return not self.is_busy

    def forget(self, structure: Structure) -> None:
        """The structure left the workspace: stop its fit (its runner ends with it)."""
        runner = self._runners.get(structure.id)
        if runner is not None:
            runner.cancel()

    def schedule(self, structure: Structure | None = None) -> int | None:
        """Submit a refit of the structure's points (the active one); returns its generation."""
        s = structure or self.state.active
        if s.model is None:
            return None
        runner = self.runner_for(s)
        if len(s.points) == 0:
            runner.cancel()
            s.set_fit_info(FitInfo(message=""))
            return None
        from core.reconstruction import MIN_POINTS, fit_points

        settings = self.settings()
        need = MIN_POINTS.get(settings["pose"], 1)
        if len(s.points) < need:           # not an error: the user is still drawing
            runner.cancel()
            s.set_fit_info(FitInfo(level="info", message=(
                f"Draw {need - len(s.points)} more point(s): a fit with pose "
                f"'{settings['pose']}' needs at least {need}.")))
            return None
        model, version = s.model, s.model_version
        points = s.points.xyz.copy()
        normals = s.point_normals()
        init = self._warm_start(s)
        placement = None if s.placement is None else s.placement.copy()
        edit_time = time.perf_counter()

        def job(progress):
            def callback(iteration: int, objective: float) -> None:
                progress(min(iteration / 100.0, 1.0), "")

            result = fit_points(model, points, normals, method=settings["method"],
                                pose=settings["pose"], prior_weight=settings["prior_weight"],
                                placement=placement, pose_spread=settings["pose_spread"],
                                init=init, callback=callback)
            return result, edit_time, version

        generation = runner.submit(job)
        self.submitted.emit()
        return generation

    @staticmethod
    def _warm_start(s: Structure):
        """The FitResult to start from: the last fit if the surface still is that fit."""
        from core.reconstruction import FitResult

        last = s.last_fit
        if last is not None and np.array_equal(last.coef, s.coef) and np.array_equal(last.pose, s.pose):
            return last
        return FitResult(coef=s.coef.copy(), pose=s.pose.copy(), vertices=s.surface_vertices().copy())

    def _on_result(self, s: Structure, value) -> None:
        result, edit_time, version = value
        if s not in self.state.structures or s.model is None or s.model_version != version \
                or np.shape(result.coef) != (s.model.n_factors,):
            return
        if not (np.all(np.isfinite(result.vertices)) and np.all(np.isfinite(result.pose))):
            self._on_failed(s, "the fit diverged (non-finite result); previous fit kept")
            return
        s.last_fit = result
        s.set_surface(result.coef, result.pose, result.vertices)
        elapsed = time.perf_counter() - edit_time
        self.refit_times.append(elapsed)
        info = FitInfo.from_result(result, elapsed)
        if s.manual_edit:                   # say that the slider values were refitted
            s.manual_edit = False
            info.level, info.message = "info", ("Refitted from your slider values: the points "
                                                "now set the factors (untick 'Refit on every "
                                                "edit' to keep shapes set by hand).")
        s.set_fit_info(info)
        self.applied.emit(result)

    def _on_failed(self, s: Structure, message: str) -> None:
        if s in self.state.structures:
            s.set_fit_info(FitInfo(message=message))
        self.failed.emit(message)

    def _on_busy(self, busy: bool) -> None:
        self.busy.emit(busy and True or self.is_busy)
