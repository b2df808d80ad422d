"""Label maps to training surfaces: one label -> one closed surface in world RAS mm.

For ``ssm-studio mesh-labels`` and the builder's *Add label maps...*. Steps, for one label
value of a label map (any volume format :func:`core.io.load_volume` reads: NIfTI, NRRD,
Slicer ``.seg.nrrd``, MetaImage, ...):

1. crop to the label's bounding box (plus a margin), so the cost follows the structure and
   not the image (a 256^3 map with one structure costs what the structure costs);
2. VTK's Surface Nets (Frisken, "SurfaceNets for multi-label segmentations with
   preservation of sharp boundaries", J. Computer Graphics Techniques 2022) on the binary
   mask, without its own constrained smoothing (which shrinks small structures);
3. windowed-sinc smoothing (Taubin, Zhang & Golub, "Optimal surface smoothing as filter
   design", ECCV 1996; ``vtkWindowedSincPolyDataFilter``): a low-pass filter without the
   shrinkage of Laplacian smoothing, which removes the voxel staircase;
4. voxel indices -> world RAS mm through the volume's affine (oblique and LPS-stored images
   included: the readers give the RAS affine), faces turned outward if the affine flips;
5. remeshed to an even density of ``n_vertices`` (:func:`core.correspondence.grooming.remesh`).

Labels are chosen by number, or by name: Slicer segment names from a ``.seg.nrrd`` header,
otherwise FreeSurfer colour-table names (``FreeSurferColorLUT.txt`` from ``$FREESURFER_HOME``
or beside the label map when present, else the built-in ``aseg`` subset below).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from core.geometry import mesh as meshops
from core.types import TriMesh, Volume

# The subcortical (aseg) part of FreeSurfer's FreeSurferColorLUT.txt: value -> name.
FREESURFER_ASEG = {
    0: "Unknown", 2: "Left-Cerebral-White-Matter", 3: "Left-Cerebral-Cortex",
    4: "Left-Lateral-Ventricle", 5: "Left-Inf-Lat-Vent", 7: "Left-Cerebellum-White-Matter",
    8: "Left-Cerebellum-Cortex", 10: "Left-Thalamus", 11: "Left-Caudate", 12: "Left-Putamen",
    13: "Left-Pallidum", 14: "3rd-Ventricle", 15: "4th-Ventricle", 16: "Brain-Stem",
    17: "Left-Hippocampus", 18: "Left-Amygdala", 24: "CSF", 26: "Left-Accumbens-area",
    28: "Left-VentralDC", 30: "Left-vessel", 31: "Left-choroid-plexus",
    41: "Right-Cerebral-White-Matter", 42: "Right-Cerebral-Cortex",
    43: "Right-Lateral-Ventricle", 44: "Right-Inf-Lat-Vent", 46: "Right-Cerebellum-White-Matter",
    47: "Right-Cerebellum-Cortex", 49: "Right-Thalamus", 50: "Right-Caudate",
    51: "Right-Putamen", 52: "Right-Pallidum", 53: "Right-Hippocampus", 54: "Right-Amygdala",
    58: "Right-Accumbens-area", 60: "Right-VentralDC", 62: "Right-vessel",
    63: "Right-choroid-plexus", 72: "5th-Ventricle", 77: "WM-hypointensities",
    85: "Optic-Chiasm", 251: "CC_Posterior", 252: "CC_Mid_Posterior", 253: "CC_Central",
    254: "CC_Mid_Anterior", 255: "CC_Anterior",
}
# Older FreeSurfer versions' names for the same values.
FREESURFER_ALIASES = {"left-thalamus-proper": 10, "right-thalamus-proper": 49}


class LabelError(ValueError):
    """A label that is missing, empty or ambiguous in a label map (message names both)."""


def _read_lut(path: Path) -> dict[str, int]:
    names = {}
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].isdigit():
            names[parts[1].lower()] = int(parts[0])
    return names


def freesurfer_names(label_map: str | os.PathLike | None = None) -> dict[str, int]:
    """Lower-case FreeSurfer label name -> value (a colour table file if found, else aseg)."""
    candidates = []
    if label_map is not None:
        candidates.append(Path(label_map).parent / "FreeSurferColorLUT.txt")
    if os.environ.get("FREESURFER_HOME"):
        candidates.append(Path(os.environ["FREESURFER_HOME"]) / "FreeSurferColorLUT.txt")
    for path in candidates:
        if path.is_file():
            return _read_lut(path)
    names = {name.lower(): value for value, name in FREESURFER_ASEG.items()}
    names.update(FREESURFER_ALIASES)
    return names


def resolve_label(label_map: str | os.PathLike, label: str | int) -> tuple[int, str]:
    """The label value and a display name for ``label`` (a number or a name) in a file.

    In a Slicer ``.seg.nrrd`` the label is a segment (:func:`slicer_segment`); its value is
    the segment's LabelValue in its own layer.
    """
    path = Path(label_map)
    text = str(label).strip()
    if _is_seg(path):
        segment = slicer_segment(path, text)
        return segment.label_value, segment.name
    if text.lstrip("-").isdigit():
        value = int(text)
        return value, FREESURFER_ASEG.get(value, f"label {value}")
    names = freesurfer_names(path)
    if text.lower() in names:
        return names[text.lower()], text
    raise LabelError(f"{path}: {text!r} is neither a label number nor a FreeSurfer label name")


def slicer_segment(path: str | os.PathLike, wanted: str | int):
    """The segment of a ``.seg.nrrd`` that ``wanted`` names (Name, ID or label value; see
    :func:`core.io.nrrd.find_segment`); :class:`LabelError` when none or several do."""
    from core.io.nrrd import SegmentChoiceError, find_segment, nrrd_layer_count, slicer_segments

    path = Path(path)
    try:
        return find_segment(path, slicer_segments(path), wanted, nrrd_layer_count(path))
    except SegmentChoiceError as exc:
        raise LabelError(str(exc)) from None


def _is_seg(path: Path) -> bool:
    return path.name.lower().endswith(".seg.nrrd")


def _vtk_image(mask: np.ndarray):
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData

    image = vtkImageData()
    image.SetDimensions(*mask.shape)
    image.GetPointData().SetScalars(numpy_to_vtk(np.asfortranarray(mask).ravel(order="F"), deep=True))
    return image


def _polydata_arrays(poly) -> tuple[np.ndarray, np.ndarray]:
    from vtkmodules.util.numpy_support import vtk_to_numpy

    if poly.GetNumberOfPoints() == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    v = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
    f = vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
    return v, f


def mask_surface(mask: np.ndarray, affine: np.ndarray, *, smoothing_iterations: int = 30,
                 pass_band: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Smooth closed surface (vertices in world mm, faces outward) of a binary mask (I, J, K).

    Surface Nets + windowed-sinc smoothing (module docstring, steps 2-4), before remeshing.
    """
    # The two filters' own module, not the whole of ``vtk`` (about 1 s less to import).
    from vtkmodules.vtkFiltersCore import vtkSurfaceNets3D, vtkWindowedSincPolyDataFilter

    padded = np.pad(np.asarray(mask, dtype=np.uint8), 1)
    nets = vtkSurfaceNets3D()
    nets.SetInputData(_vtk_image(padded))
    nets.SetValue(0, 1)
    nets.SetOutputMeshTypeToTriangles()
    nets.SetSmoothing(False)
    nets.Update()
    smoother = vtkWindowedSincPolyDataFilter()
    smoother.SetInputData(nets.GetOutput())
    smoother.SetNumberOfIterations(int(smoothing_iterations))
    smoother.SetPassBand(float(pass_band))
    smoother.NormalizeCoordinatesOn()
    smoother.BoundarySmoothingOff()
    smoother.FeatureEdgeSmoothingOff()
    smoother.NonManifoldSmoothingOn()
    smoother.Update()
    v, f = _polydata_arrays(smoother.GetOutput())
    v = (v - 1.0) @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3]
    if len(f) and meshops.volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, f


def label_surface(volume: Volume, value: int, *, n_vertices: int | None = 2000,
                  name: str = "", source: str = "label map", info: dict | None = None,
                  label_name: str | None = None) -> TriMesh:
    """One label of a label map as a closed surface in world RAS mm (module docstring).

    ``n_vertices`` None keeps the Surface Nets resolution (about one vertex per boundary
    voxel face). Separate pieces of the label: the largest is kept, and ``info`` (if given)
    gets ``voxels``, ``dropped_pieces`` and ``dropped_area_share``. Raises
    :class:`LabelError` naming ``source`` and the label when the label has no voxel.
    """
    from core.correspondence.grooming import largest_piece, remesh, weld

    data = np.asarray(volume.data)
    mask = data == value
    if not mask.any():
        present = np.unique(data)
        shown = ", ".join(str(int(p)) for p in present[:20]) + (" ..." if len(present) > 20 else "")
        raise LabelError(f"{source}: label {label_name or value} (value {value}) has no voxel "
                         f"(values present: {shown})")
    # Bounding box from the three axis projections (argwhere would list every voxel).
    spans = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
             for axis in range(3)]
    lo = np.maximum([s[0] - 1 for s in spans], 0)
    hi = np.minimum([s[-1] + 2 for s in spans], mask.shape)
    crop = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    shift = np.eye(4)
    shift[:3, 3] = lo
    v, f = mask_surface(crop, np.asarray(volume.affine) @ shift)
    v, f, _, _ = weld(v, f)
    v, f, dropped, _, share = largest_piece(v, f)
    if info is not None:
        info.update(voxels=int(np.count_nonzero(crop)), dropped_pieces=int(dropped),
                    dropped_area_share=float(share))
    if n_vertices is not None and len(v) >= 4:
        v, f = remesh(v, f, int(n_vertices))
    return TriMesh(v, f, name or f"label_{value}")


def label_map_surface(path: str | os.PathLike, label: str | int, *, n_vertices: int | None = 2000,
                      info: dict | None = None) -> TriMesh:
    """Read a label map file and return one label's surface (the builder's *Add label maps*).

    The mesh is named ``<file stem>_<label name>``; errors name the file and the label.
    """
    from core.io import load_volume

    value, name = resolve_label(path, label)
    if _is_seg(Path(path)):  # the segment's own layer (overlapping segments: 4-D files)
        from core.io.nrrd import read_segmentation

        segmentation = read_segmentation(path)
        segment = segmentation.find(label)
        mask = segmentation.mask(segment).astype(np.uint16) * np.uint16(segment.label_value)
        volume = Volume(mask, segmentation.affine, Path(path))
    else:
        volume = load_volume(path)
    stem = Path(path).name.split(".")[0]
    safe = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in name)
    return label_surface(volume, value, n_vertices=n_vertices, name=f"{stem}_{safe}",
                         source=str(path), info=info, label_name=name)


def label_map_surfaces(paths: list, label: str | int, *, n_vertices: int | None = 2000,
                       progress=None) -> list[tuple[str, TriMesh | None, str | None]]:
    """:func:`label_map_surface` for several files: (path, mesh or None, error or None) each,
    so that one bad file does not stop the others (the builder's *Add label maps...*)."""
    from core.runtime.progress import report

    out = []
    for i, path in enumerate(paths):
        report(progress, i / max(len(paths), 1), f"meshing {Path(path).name}")
        try:
            out.append((str(path), label_map_surface(path, label, n_vertices=n_vertices), None))
        except (ValueError, OSError) as exc:
            out.append((str(path), None, " ".join(str(exc).split())))
    report(progress, 1.0, "meshed")
    return out
