"""The planning model of the workspace: AC, PC, midline, and a target and entry per structure.

Plain Python, no Qt (like :mod:`app.model.state`; a test checks it). :class:`PlanningState` sits next
to the :class:`app.model.state.WorkspaceState` and refers to its structures by identity:

- landmarks ``ac``, ``pc``, ``midline`` (world RAS mm, or None); with all three set and valid,
  :meth:`PlanningState.frame` is the AC-PC frame (``core.planning.frames.ACPCFrame``) and every read-out
  also gives AC-PC coordinates;
- per structure an optional user target (None: the model's default target, which moves with
  the fitted surface: the target stored in the model file, else the fitted surface's
  centroid; ``core.planning.report.model_target``) and an optional entry point; with both, the
  structure has a trajectory;
- per structure an optional lead on its trajectory (``core.planning.report.LeadChoice``: type,
  tip depth past the target, rotation of directional segments; placed by
  ``core.planning.lead.place_lead``);
- its own undo history of these edits (the structures' undo stacks stay theirs).

Events (``planning.events.<name>.connect``): ``landmarks``, ``trajectory(structure)``,
``history``, ``edited(what)``. Every read-out is computed by ``core.planning.frames`` /
``core.planning.report`` (no maths here).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from app.model.events import EmitterGroup
from app.model.history import UndoHistory
from app.model.state import Structure, WorkspaceState
from core.io.model_library import structure_info
from core.planning.frames import (
    ACPCFrame,
    PlanningError,
    Surface,
    Trajectory,
    template_ventricles,
    trajectory_warnings,
)
from core.planning.lead import PlacedLead, contact_readout, place_lead
from core.planning.report import LeadChoice, PlannedStructure, model_target, plan_report, template_to_image

LANDMARKS = ("ac", "pc", "midline")
LANDMARK_LABELS = {"ac": "AC", "pc": "PC", "midline": "Midline"}


@dataclass
class _Snapshot:
    landmarks: dict
    targets: dict
    entries: dict
    leads: dict


@dataclass(eq=False)
class PlanningState:
    """Evented planning state (see the module docstring)."""

    workspace: WorkspaceState
    landmarks: dict = field(default_factory=lambda: {name: None for name in LANDMARKS})
    targets: dict = field(default_factory=dict)     # structure id -> (3,) world
    entries: dict = field(default_factory=dict)     # structure id -> (3,) world
    leads: dict = field(default_factory=dict)       # structure id -> LeadChoice

    def __post_init__(self) -> None:
        self.events = EmitterGroup(landmarks=(), trajectory=("structure",), history=(),
                                   edited=("what",))
        self.history = UndoHistory(self._snapshot, self._restore, self.events.history)
        self._default_targets: dict = {}    # (structure, model, surface version) -> world
        self._ventricles_cache: tuple = (None, None)    # (placement key, Surface)
        self.workspace.events.structure_changed.connect(self._on_structure)
        self.workspace.events.structures.connect(self._on_structures)

    # -- landmarks and the AC-PC frame ------------------------------------------------------
    def set_landmark(self, name: str, xyz) -> None:
        """Set (or clear, with None) AC, PC or the midline point (undoable)."""
        if name not in LANDMARKS:
            raise ValueError(f"unknown landmark {name!r}, expected one of {LANDMARKS}")
        self._checkpoint()
        self.landmarks[name] = None if xyz is None else np.asarray(xyz, dtype=np.float64).copy()
        self.events.landmarks()
        for s in self.workspace.structures:
            self.events.trajectory(s)
        self.events.edited("landmarks")

    def frame(self) -> ACPCFrame | None:
        """The AC-PC frame, or None while a landmark is missing or the three are degenerate."""
        try:
            return self._frame()
        except PlanningError:
            return None

    def frame_problem(self) -> str | None:
        """Why there is no AC-PC frame (a sentence for the user), or None when there is one."""
        missing = [LANDMARK_LABELS[n] for n in LANDMARKS if self.landmarks[n] is None]
        if missing:
            return "set " + ", ".join(missing) + " for AC-PC coordinates"
        try:
            self._frame()
        except PlanningError as exc:
            return str(exc)
        return None

    def _frame(self) -> ACPCFrame:
        if any(self.landmarks[n] is None for n in LANDMARKS):
            raise PlanningError("AC, PC and the midline point are not all set")
        return ACPCFrame.from_points(self.landmarks["ac"], self.landmarks["pc"],
                                     self.landmarks["midline"])

    # -- targets, entries, trajectories -------------------------------------------------------
    def set_target(self, structure: Structure, xyz) -> None:
        """A user target for ``structure`` (None: back to the model's default target)."""
        self._checkpoint()
        if xyz is None:
            self.targets.pop(structure.id, None)
        else:
            self.targets[structure.id] = np.asarray(xyz, dtype=np.float64).copy()
        self.events.trajectory(structure)
        self.events.edited("target")

    def set_entry(self, structure: Structure, xyz) -> None:
        """The entry point of ``structure``'s trajectory (None: no trajectory)."""
        self._checkpoint()
        if xyz is None:
            self.entries.pop(structure.id, None)
        else:
            self.entries[structure.id] = np.asarray(xyz, dtype=np.float64).copy()
        self.events.trajectory(structure)
        self.events.edited("entry")

    def set_lead(self, structure: Structure, choice: LeadChoice | None) -> None:
        """The lead on ``structure``'s trajectory (None: no lead); undoable."""
        if choice is not None:
            place_lead(Trajectory([0, 0, 1.0], [0, 0, 0]), choice.lead, choice.depth_mm,
                       choice.rotation_deg)          # refuses an unknown type or depth now
        if self.leads.get(structure.id) == choice:
            return
        self._checkpoint()
        if choice is None:
            self.leads.pop(structure.id, None)
        else:
            self.leads[structure.id] = choice
        self.events.trajectory(structure)
        self.events.edited("lead")

    def lead_of(self, structure: Structure) -> LeadChoice | None:
        return self.leads.get(structure.id)

    def placed_lead_of(self, structure: Structure) -> PlacedLead | None:
        """The structure's lead placed on its trajectory (None without lead or trajectory)."""
        choice, traj = self.lead_of(structure), self.trajectory_of(structure)
        if choice is None or traj is None:
            return None
        return place_lead(traj, choice.lead, choice.depth_mm, choice.rotation_deg)

    def contact_rows(self, structure: Structure) -> list[dict]:
        """``core.planning.lead.contact_readout`` of the structure's lead ([] without one)."""
        placed = self.placed_lead_of(structure)
        if placed is None:
            return []
        return contact_readout(placed, self.planned_structures(), self.frame(),
                               self.workspace.volume)

    def warnings_of(self, structure: Structure) -> list[dict]:
        """``core.planning.frames.trajectory_warnings`` of the structure's trajectory against
        every fitted structure ([] without a trajectory)."""
        traj = self.trajectory_of(structure)
        if traj is None:
            return []
        own = self._planned(structure) if structure.model is not None else None
        return trajectory_warnings(traj, own, self.planned_structures() + self._ventricles())

    def _ventricles(self) -> list[Surface]:
        """The demo template's ventricles where the library models put the template (the
        placement of the first one in its space, as ``ssm-studio plan`` checks them); [] when
        no structure comes from the template. Kept while that placement stays."""
        placement = template_to_image(self.workspace)
        if placement is None:
            return []
        key = placement.round(6).tobytes()
        if self._ventricles_cache[0] != key:
            self._ventricles_cache = (key, template_ventricles(placement))
        return [self._ventricles_cache[1]]

    def target_is_default(self, structure: Structure) -> bool:
        return structure.id not in self.targets

    def target_of(self, structure: Structure) -> np.ndarray | None:
        """World target: the user's, else the model's default on the fitted surface."""
        if structure.id in self.targets:
            return self.targets[structure.id]
        model = structure.model
        if model is None:
            return None
        # cached per surface: views ask on every paint (the centroid costs ~ms per call)
        key = (structure.id, structure.model_version, structure._surface_version)
        cache = self._default_targets
        if key not in cache:
            local = model.instance(structure.coef)
            target = model_target(model.mean, model.faces, local, structure_info(model).target)
            if len(cache) > 64:
                cache.clear()
            cache[key] = target @ structure.pose[:3, :3].T + structure.pose[:3, 3]
        return cache[key]

    def entry_of(self, structure: Structure) -> np.ndarray | None:
        return self.entries.get(structure.id)

    def trajectory_of(self, structure: Structure) -> Trajectory | None:
        target, entry = self.target_of(structure), self.entry_of(structure)
        if target is None or entry is None:
            return None
        try:
            return Trajectory(entry, target)
        except PlanningError:
            return None

    def planned_structures(self) -> list[PlannedStructure]:
        """The fitted structures with their targets and entries, for reports and exports."""
        return [self._planned(s) for s in self.workspace.structures if s.model is not None]

    def _planned(self, s: Structure) -> PlannedStructure:
        return PlannedStructure(s.label, s.surface_vertices(), s.model.faces,
                                tuple(c / 255.0 for c in s.color),
                                target=self.target_of(s), entry=self.entry_of(s))

    def report(self) -> dict:
        """The plan report (``core.planning.report.plan_report``) of the current workspace."""
        image = str(self.workspace.image_path.name) if self.workspace.image_path else None
        return plan_report(self.planned_structures(), self.frame(), image)

    # -- undo ---------------------------------------------------------------------------------
    def _snapshot(self) -> _Snapshot:
        return _Snapshot(dict(self.landmarks), dict(self.targets), dict(self.entries),
                         dict(self.leads))

    def _checkpoint(self) -> None:
        self.history.checkpoint()

    def can_undo(self) -> bool:
        return self.history.can_undo()

    def can_redo(self) -> bool:
        return self.history.can_redo()

    def undo(self) -> bool:
        return self.history.undo()

    def redo(self) -> bool:
        return self.history.redo()

    def _restore(self, snap: _Snapshot) -> None:
        self.landmarks, self.targets, self.entries = snap.landmarks, snap.targets, snap.entries
        self.leads = snap.leads
        self.events.landmarks()
        for s in self.workspace.structures:
            self.events.trajectory(s)
        self.events.history()
        self.events.edited("planning")

    # -- sessions -----------------------------------------------------------------------------
    def to_document(self) -> dict:
        """The session's ``planning`` block; structures by their index in the structure list."""
        index = {s.id: i for i, s in enumerate(self.workspace.structures)}

        def vec(v):
            return None if v is None else [float(c) for c in v]

        per_structure = []
        for sid in sorted(set(self.targets) | set(self.entries) | set(self.leads),
                          key=lambda k: index.get(k, 1e9)):
            if sid not in index:
                continue
            item = {"structure": index[sid], "target": vec(self.targets.get(sid)),
                    "entry": vec(self.entries.get(sid))}
            lead = self.leads.get(sid)
            if lead is not None:     # optional key: older sessions have none
                item["lead"] = {"type": lead.lead, "depth_mm": float(lead.depth_mm),
                                "rotation_deg": float(lead.rotation_deg)}
            per_structure.append(item)
        return {**{name: vec(self.landmarks[name]) for name in LANDMARKS},
                "structures": per_structure}

    def apply_document(self, doc: dict | None) -> None:
        """Restore from a session's ``planning`` block (None or {}: nothing planned)."""
        doc = doc or {}
        landmarks = {name: (None if doc.get(name) is None else np.asarray(doc[name], float))
                     for name in LANDMARKS}
        targets, entries, leads = {}, {}, {}
        structures = self.workspace.structures
        for item in doc.get("structures", []):
            i = int(item["structure"])
            if not 0 <= i < len(structures):
                raise ValueError(f"planning refers to structure {i + 1}, the session has "
                                 f"{len(structures)}")
            sid = structures[i].id
            if item.get("target") is not None:
                targets[sid] = np.asarray(item["target"], dtype=np.float64)
            if item.get("entry") is not None:
                entries[sid] = np.asarray(item["entry"], dtype=np.float64)
            lead = item.get("lead")
            if lead:
                leads[sid] = LeadChoice(str(lead["type"]), float(lead.get("depth_mm", 0.0)),
                                        float(lead.get("rotation_deg", 0.0)))
        self.landmarks, self.targets, self.entries = landmarks, targets, entries
        self.leads = leads
        self.history.clear()
        self.events.landmarks()
        for s in structures:
            self.events.trajectory(s)

    # -- following the workspace ------------------------------------------------------------
    def _on_structure(self, structure: Structure, what: str) -> None:
        if what in ("surface", "model"):
            self.events.trajectory(structure)   # a model target moves with the surface

    def _on_structures(self) -> None:
        alive = {s.id for s in self.workspace.structures}
        self.targets = {k: v for k, v in self.targets.items() if k in alive}
        self.entries = {k: v for k, v in self.entries.items() if k in alive}
        self.leads = {k: v for k, v in self.leads.items() if k in alive}
