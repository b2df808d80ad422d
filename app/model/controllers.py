"""Session and export logic of the segmentation workspace (3D Slicer's *Logic*; no Qt).

The window's actions call these with file paths; they read and write through ``core`` and
change the :class:`app.model.state.WorkspaceState`, raise ``ValueError``/``OSError`` (a
``core.io.DataFileError`` names the file) for the window to show, and return the one-line
message for the status bar. The refit, which needs a worker thread, is in
:mod:`app.refit`.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from app.model.state import FRAME_NAMES, STRUCTURE_COLORS, FitInfo, Points, Structure, WorkspaceState
from core.geometry.planes import PLANE_NAMES
from core.io import DataFileError, load_model, load_volume, save_mesh, save_points, save_volume
from core.io.registry import split_member  # a FILE.h5#GROUP model path names FILE

RECOVERED_PATH_KEY = "session_path"     # in a recovery file's info: the session's own file


def read_image(path: str | os.PathLike, series: str | None = None,
               default_of: str | os.PathLike | None = None, progress=None):
    """The image at ``path`` (:func:`core.io.load_volume`), for a worker thread. ``default_of``:
    the DICOM folder whose series ``path`` was taken by default, which an error then names
    with the folder's other series. A Cancel while the file is read (``progress`` raises at
    its next call) drops the image read."""
    from app import formats

    if progress is not None:
        progress(0.0, "")
    try:
        volume = load_volume(path, series=series)
    except DataFileError as exc:
        if default_of is None:
            raise
        raise formats.default_series_error(default_of, path, exc) from None
    if progress is not None:
        progress(1.0, "")
    return volume


class SessionController:
    """What is open: the image, the structures' models, the session file and its recovery."""

    def __init__(self, state: WorkspaceState):
        self.state = state
        # extra blocks of the session's ``info`` (e.g. "planning"): key -> callable giving it
        self.info_providers: dict[str, Callable[[], Any]] = {}
        # and read back by key when a session is applied (``read(session.info.get(key))``)
        self.info_readers: dict[str, Callable[[Any], None]] = {}
        self._recovery = None  # core.session.recovery.CrashRecovery, made on first use

    @property
    def recovery(self):
        """This process's crash-recovery autosave (:class:`core.session.recovery.CrashRecovery`)."""
        if self._recovery is None:
            from core.session.recovery import CrashRecovery

            self._recovery = CrashRecovery()
        return self._recovery

    # -- image and models --------------------------------------------------------------
    def open_image(self, path: str | os.PathLike, series: str | None = None,
                   volume=None) -> str:
        """Load an image (NIfTI, NRRD, MetaImage, DICOM series; raises DataFileError), or show
        ``volume`` already read from it (:func:`read_image` in a worker); the crosshair goes
        to the model. A DICOM image is named by its series description only (app.formats),
        never by its folder or file name."""
        from app import formats

        if volume is None:
            volume = load_volume(path, series=series)
        name = formats.remember_display_name(path)  # before set_image updates the title
        self.state.set_image(volume, path)
        self.center_on_model()
        if not volume.orientation_known:
            return (f"Warning: {name} has neither sform nor qform: its orientation "
                    "is unknown, LEFT AND RIGHT MAY BE SWAPPED. Views show '?' for the sides; "
                    "exports ask for confirmation.")
        return (f"Opened {name}: {volume.shape[0]}x{volume.shape[1]}x"
                f"{volume.shape[2]} voxels, {' '.join(f'{s:.2g}' for s in volume.spacing)} mm")

    def open_model(self, path: str | os.PathLike, coef=None, pose=None,
                   structure: Structure | None = None) -> str:
        """Load a shape model into ``structure`` (the active one) at its stored placement: one
        undo step; the structure takes the model's name, side and colour unless the user set
        them."""
        model = load_model(path)
        structure = structure or self.state.active
        structure.replace_model(model, path, coef=coef, pose=pose)
        self.center_on_model()
        warning = self.overlap_warning(structure)
        if warning:
            return warning
        return (f"Loaded model {Path(path).name}: {model.method}, "
                f"{model.n_factors} factors, {model.n_vertices} vertices")

    def overlap_warning(self, structure: Structure | None = None) -> str:
        """A warning when a structure's model and the image do not overlap at all, else ""."""
        volume = self.state.volume
        for s in [structure] if structure is not None else self.state.structures:
            vertices = s.surface_vertices()
            if vertices is None or volume is None:
                continue
            lo, hi = volume.world_bounds()
            if np.any(vertices.max(axis=0) < lo) or np.any(vertices.min(axis=0) > hi):
                name = s.model_path.name if s.model_path else s.label
                return (f"Warning: model {name} and the image do not overlap (the model is "
                        f"outside the image): use 'Place here' to move it to the crosshair")
        return ""

    def center_on_model(self) -> None:
        vertices = self.state.active.surface_vertices()
        if vertices is not None and self.state.volume is not None:
            self.state.set_crosshair(vertices.mean(axis=0))

    def add_structure(self, path: str | os.PathLike) -> tuple[Structure, str]:
        """A new active structure with the model file ``path`` (name, side and colour from its
        header, :meth:`app.model.state.Structure.set_model`), at the model's stored placement; its
        first undo step removes it again."""
        model = load_model(path)
        structure = Structure()
        self.state.add_structure(structure)
        structure.set_model(model, path)
        structure.mark_added()
        self.center_on_model()
        kind = "demo model" if structure.demo else f"{model.method} model"
        return structure, f"Added {structure.label}: {kind}, {model.n_factors} factors"

    # -- sessions ----------------------------------------------------------------------
    def to_session(self, fit_settings: dict):
        """The current work as a :class:`core.session.document.Session`.

        The top level holds the active structure (as single-structure sessions always did);
        with several structures, or a renamed/recoloured one, ``structures`` holds them all.
        """
        from core.session.document import Session, SessionStructure

        state = self.state
        s = state.active
        records = []
        if len(state.structures) > 1 or s.customised:
            records = [SessionStructure(
                name=st.name, side=st.side, color=tuple(c / 255 for c in st.color),
                visible=st.visible, locked=st.locked, model_path=st.model_path,
                points=st.points.xyz.copy(), normals=st.point_normals() if len(st.points) else None,
                point_slices=_point_slices(st.points), coef=st.coef, pose=st.pose,
                placement=st.placement) for st in state.structures]
        pts = s.points
        return Session(
            image_path=state.image_path, model_path=s.model_path,
            points=pts.xyz.copy(), normals=s.point_normals() if len(pts) else None,
            point_slices=_point_slices(pts),
            coef=None if s.coef is None else s.coef.copy(),
            pose=None if s.pose is None else s.pose.copy(),
            fit=dict(fit_settings), window=(state.window, state.level),
            crosshair=state.crosshair.copy(),
            info={"written_by": "ssm-studio",
                  **{key: provide() for key, provide in self.info_providers.items()}},
            structures=records, active_structure=state.structures.index(s) if records else 0,
        )

    def apply(self, session, volume=None) -> dict:
        """Restore image, structures (models, points, fits), window and crosshair; returns
        the fit settings. The stored fits are shown as saved (no refit), and every undo
        history starts empty. ``volume``: the session's image, read already (in a worker).
        """
        if session.image_path is not None:
            self.open_image(session.image_path, volume=volume)
        records = session.structures or [_top_level_record(session)]
        models: dict[Path, object] = {}
        structures = []
        for record in records:
            structure = Structure(name=record.name, side=record.side)
            if record.color is not None:
                structure.color = tuple(int(round(255 * c)) for c in record.color)
                structure.customised = bool(session.structures)
            structure.visible, structure.locked = record.visible, record.locked
            if record.model_path is not None:
                key = Path(os.path.abspath(record.model_path))
                if key not in models:
                    models[key] = load_model(record.model_path)
                structure.set_model(models[key], record.model_path, coef=record.coef, pose=record.pose)
                if record.placement is not None:
                    structure.placement = np.asarray(record.placement, dtype=np.float64).copy()
            structure.points = _points(record.points, record.point_slices)
            structures.append(structure)
        used: set = set()
        for structure in structures:                     # distinct colours
            if structure.color in used:
                structure.color = next((c for c in STRUCTURE_COLORS if c not in used), structure.color)
            used.add(structure.color)
        for structure in structures:         # the stored fit, read out (not "no fit yet")
            if structure.model is not None and len(structure.points):
                structure.fit_info = FitInfo(residual_mm=structure.residual_mm(), kind="restored")
        self.state.replace_structures(structures, session.active_structure if session.structures else 0)
        self.center_on_model()
        if session.window is not None:
            self.state.set_window(*session.window)
        if session.crosshair is not None:
            self.state.set_crosshair(session.crosshair)
        for key, read in self.info_readers.items():
            read((session.info or {}).get(key))
        self.state.clear_history()
        return dict(session.fit or {})

    @staticmethod
    def read(path: str | os.PathLike):
        from core.session import document as sessions

        session = sessions.load_session(path)
        if session.model_path is not None and split_member(session.model_path)[0].exists():
            # refuse a session that does not fit its model before applying any of it
            sessions.check_session_model(session, load_model(session.model_path), path)
        for k, st in enumerate(session.structures):
            if st.model_path is not None and split_member(st.model_path)[0].exists() and st.coef is not None:
                n_factors = load_model(st.model_path).n_factors
                if st.coef.shape[0] != n_factors:
                    raise DataFileError(path, f"structure {k + 1} ({st.name or 'unnamed'}) holds "
                                              f"{st.coef.shape[0]} shape coefficients but its model "
                                              f"has {n_factors} factors")
        return session

    def save(self, path: str | os.PathLike, fit_settings: dict) -> str:
        from core.session import document as sessions

        if self.state.image_path is None:
            raise ValueError("nothing to save: open an image first")
        sessions.save_session(path, self.to_session(fit_settings))
        return f"Saved session {Path(path).name}"

    def pending_recovery(self):
        """(session, question to ask) left by a run that did not exit normally, or None.

        An unreadable recovery file is discarded, then its error raised.
        """
        from core.session import document as sessions

        try:
            session = self.recovery.read()
        except (ValueError, OSError):
            self.recovery.clear()
            raise
        if session is None:
            return None
        if session.model_path is not None and split_member(session.model_path)[0].exists():
            try:  # a model rebuilt since: refuse the recovery whole, not half-way
                sessions.check_session_model(session, load_model(session.model_path),
                                             self.recovery.path)
            except (ValueError, OSError):
                self.recovery.clear()
                raise
        n_points = len(np.asarray(session.points).reshape(-1, 3))
        return session, (f"SSM Studio did not close normally last time. Restore the unsaved "
                         f"session ({n_points} contour point(s))?")

    def clear_recovery(self) -> None:
        self.recovery.clear()

    def write_recovery(self, fit_settings: dict, session_path: Path | None = None) -> None:
        """Autosave for crash recovery, with the file the session was opened from or saved
        to (``info["session_path"]``: restored with the work)."""
        session = self.to_session(fit_settings)
        if session_path is not None:
            session.info[RECOVERED_PATH_KEY] = str(Path(session_path).resolve())
        self.recovery.write(session)


def edits_path(labels_path: str | os.PathLike) -> Path:
    """Where the manual-edit marks go next to a label map: ``<name>_manual_edits.nii.gz``."""
    path = Path(labels_path)
    name = path.name
    for suffix in (".nii.gz", ".seg.nrrd"):
        if name.lower().endswith(suffix):
            name = name[:-len(suffix)]
            break
    stem = name if name != path.name else path.stem
    return path.with_name(f"{stem}_manual_edits.nii.gz")


class ExportController:
    """Label map, surface mesh and points out; points in."""

    def __init__(self, state: WorkspaceState):
        self.state = state
        # more files for Export all, each a pair ``(write(folder) -> [paths written],
        # outputs(folder) -> [paths it would write])`` (the measurements, every structure):
        # the outputs let Export all ask before overwriting any of them
        self.extra_exports: list[tuple[Callable[[Path], list[Path]],
                                       Callable[[Path], list[Path]]]] = []
        # what the last Export all could not write and why (one line each), for its message
        self.notes: list[str] = []

    def label_map(self, structure: Structure | None = None) -> np.ndarray:
        """The fitted surface as a uint8 label map on the image grid (1 inside), with the
        structure's manual brush/eraser edits applied (``core.geometry.labelmap``)."""
        from core.geometry.labelmap import structure_label_map

        s = structure or self.state.active
        if s.model is None or self.state.volume is None:
            raise ValueError("need an image and a fitted model to export a label map")
        volume = self.state.volume
        return structure_label_map(s.surface_vertices(), s.model.faces, volume.shape,
                                   volume.affine, self._edits(s))

    def _edits(self, s: Structure):
        volume = self.state.volume
        return s.edits if s.edits and volume is not None and s.edits.shape == volume.shape \
            else None

    def export_labels(self, path: str | os.PathLike) -> str:
        """The label map by extension; a .seg.nrrd carries the structure's name and colour."""
        labels = self.label_map()
        if str(path).lower().endswith(".seg.nrrd"):
            from core.io.nrrd import Segment, write_segmentation

            s = self.state.active
            name = s.name or (Path(s.model_path).name.split(".")[0] if s.model_path else "")
            write_segmentation(path, labels.astype(np.uint8), self.state.volume.affine,
                               [Segment(1, name or "Structure",
                                        tuple(c / 255.0 for c in s.color))])
        else:
            save_volume(path, labels.astype(np.uint8), self.state.volume.affine,
                        like=self.state.volume)  # the image's own sform/qform and codes
        message = f"Exported label map {Path(path).name}: {int(labels.sum())} voxels inside"
        edits = self._edits(self.state.active)
        if edits:  # marked apart: 1 = added by hand, 2 = erased by hand
            marks = edits_path(path)
            save_volume(marks, edits.edit_map(), self.state.volume.affine, like=self.state.volume)
            message += (f" (manual edits: +{len(edits.added)}/-{len(edits.removed)} voxels, "
                        f"marked in {marks.name})")
        return message

    def export_mesh(self, path: str | os.PathLike) -> str:
        from core.io import TriMesh

        s = self.state.active
        if s.model is None:
            raise ValueError("no model loaded: nothing to export")
        save_mesh(path, TriMesh(s.surface_vertices(), s.model.faces))
        return f"Exported surface {Path(path).name}"

    def export_points(self, path: str | os.PathLike) -> str:
        s = self.state.active
        if len(s.points) == 0:
            raise ValueError("no contour points to export")
        save_points(path, s.points.xyz, s.point_normals())
        return f"Exported {len(s.points)} points to {Path(path).name}"

    def nothing_to_export(self, what: str = "all") -> str:
        """Why there is nothing to export (``what``: labels, mesh, points, all), or ""."""
        state = self.state
        if state.volume is None and what in ("labels", "all"):
            return "nothing to export: open an image first"
        if state.active.model is None and what in ("labels", "mesh"):
            return "nothing to export: load a model first"
        if what == "points" and len(state.active.points) == 0:
            return "no contour points to export"
        if what == "all" and state.active.model is None and len(state.active.points) == 0:
            return "nothing to export: load a model or draw contour points first"
        return ""

    def outputs(self, folder: str | os.PathLike) -> list[Path]:
        """The files :meth:`export_all` writes into ``folder``."""
        folder = Path(folder)
        names = []
        if self.state.active.model is not None and self.state.volume is not None:
            names += ["segmentation.nii.gz", "surface.vtk"]
        if len(self.state.active.points):
            names += ["points.csv", "points.mrk.json"]
        return [folder / name for name in names] + [
            p for _, outputs in self.extra_exports for p in outputs(folder)]

    def existing_outputs(self, folder: str | os.PathLike) -> list[Path]:
        """Files of an earlier export that :meth:`export_all` would overwrite."""
        return [p for p in self.outputs(folder) if p.exists()]

    def export_all(self, folder: str | os.PathLike) -> list[Path]:
        """Label map, mesh and points (CSV and Slicer markups) into ``folder``."""
        folder = Path(folder)
        written = []
        self.notes = []
        if self.state.active.model is not None and self.state.volume is not None:
            written.append(folder / "segmentation.nii.gz")
            self.export_labels(written[-1])
            if self._edits(self.state.active):
                written.append(edits_path(written[-1]))
            written.append(folder / "surface.vtk")
            self.export_mesh(written[-1])
        if len(self.state.active.points):
            for name in ("points.csv", "points.mrk.json"):
                written.append(folder / name)
                self.export_points(written[-1])
        for write, _ in self.extra_exports:
            written.extend(write(folder))
        return written

    def import_points(self, path: str | os.PathLike) -> str:
        """Add points from CSV / Slicer markups, grouped by the plane each contour lies on
        (``core.geometry.planes.group_coplanar``), with the file's normals when it has them.

        A group on an axial, coronal or sagittal plane is filed on that slice (so *Clear
        slice* removes it); an oblique one on the slice of the axis closest to its normal.
        """
        from core.geometry.planes import FRAMES, group_coplanar
        from core.io import load_points

        pset = load_points(path)
        xyz = np.asarray(pset.points, dtype=np.float64).reshape(-1, 3)
        labels, normals, _ = group_coplanar(xyz)
        frames = np.zeros(len(xyz), dtype=np.int64)
        depths = np.zeros(len(xyz))
        tilted = 0
        for g, normal in enumerate(normals):
            axis = int(np.argmax(np.abs(normal)))          # 0 x: sagittal, 1 y: coronal, 2 z: axial
            name = PLANE_NAMES[axis]
            tilted += int(abs(normal[axis]) < 0.999)
            members = labels == g
            frames[members] = FRAME_NAMES.index(name)
            depths[members] = float(np.mean(FRAMES[name].depth(xyz[members])))
        given = np.full_like(xyz, np.nan) if pset.normals is None else np.asarray(pset.normals, float)
        imported = Points(xyz, frames, depths, labels, np.ones(len(xyz), dtype=bool), given)
        self.state.active.set_points(self.state.active.points.extend(imported), checkpoint=True)
        planes = len(normals)
        note = f", {tilted} oblique" if tilted else ""
        kept = ", normals kept" if pset.normals is not None else ""
        return (f"Imported {len(pset)} point(s) on {planes} plane(s){note} from "
                f"{Path(path).name} into {self.state.active.label}{kept}")


def _point_slices(points: Points) -> list[tuple[str, float]]:
    return [(FRAME_NAMES[int(f)], float(d)) for f, d in zip(points.frame, points.depth)]


def _points(xyz, slices) -> Points:
    """Points from session arrays; points without slice records go to their axial slice."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    slices = slices or [("axial", float(p[2])) for p in xyz]
    frames = [FRAME_NAMES.index(name if isinstance(name, str)
                                else PLANE_NAMES[int(name)])
              for name, _ in slices]
    return Points(xyz.copy(), np.asarray(frames, dtype=np.int64).reshape(-1),
                  np.asarray([float(d) for _, d in slices]).reshape(-1))


def _top_level_record(session):
    """The one structure of a session without a ``structures`` list."""
    from core.session.document import SessionStructure

    return SessionStructure(model_path=session.model_path, points=session.points,
                            point_slices=session.point_slices, coef=session.coef,
                            pose=session.pose)
