"""Label maps to training surfaces: one label -> one closed surface in world RAS mm.

For ``ssm-studio mesh-labels`` and the builder's *Add label maps...*. Steps, for one label
value of a label map (any volume format :func:`core.io.load_volume` reads: NIfTI, NRRD,
Slicer ``.seg.nrrd``, MetaImage, ...):

1. crop to the label's bounding box (plus a margin), so the cost follows the structure and
   not the image (a 256^3 map with one structure costs what the structure costs);
2. repair the mask the way a manual segmentation needs (:func:`repair_mask`): keep the largest
   face-connected (6-connected) piece, dropping and counting the islands; fill enclosed
   cavities; resolve every edge- or corner-only contact: the image is made *well-composed*
   (Latecki, "3D well-composed pictures", Graphical Models and Image Processing 1997: no 2x2
   diagonal pattern around an edge, no 2x2x2 cube whose two antipodal voxels alone have one
   value) by filling the critical squares and cubes, so that the boundary is a 2-manifold.
   Handles made by noise (one-voxel bridges, tunnels through flipped voxels) are removed
   where needed: the label's genus is the one it keeps under a 1-voxel opening and closing
   (handles one voxel thin are noise, thicker ones the structure's: a ring stays a ring),
   and while the mask has more handles, parts that the opening removes (bridges, spikes) and
   dents that the closing fills, up to a growing size (:data:`NOISE_SIZES` voxels), are
   removed and filled;
3. VTK's Surface Nets (Frisken, "SurfaceNets for multi-label segmentations with
   preservation of sharp boundaries", J. Computer Graphics Techniques 2022) on the binary
   mask, without its own constrained smoothing (which shrinks small structures): on a
   well-composed mask, one closed 2-manifold surface per face-connected piece;
4. windowed-sinc smoothing (Taubin, Zhang & Golub, "Optimal surface smoothing as filter
   design", ECCV 1996; ``vtkWindowedSincPolyDataFilter``): a low-pass filter without the
   shrinkage of Laplacian smoothing, which removes the voxel staircase (vertices move, the
   topology does not change);
5. voxel indices -> world RAS mm through the volume's affine (oblique and LPS-stored images
   included: the readers give the RAS affine), faces turned outward if the affine flips;
6. remeshed to an even density of ``n_vertices`` (:func:`core.correspondence.grooming.remesh`, which keeps
   the topology), and checked (:func:`core.geometry.mesh.topology`: every edge on two triangles,
   every vertex one fan, consistent orientation, Euler characteristic 2 - 2 genus).

Labels are chosen by number, or by name: Slicer segment names from a ``.seg.nrrd`` header,
otherwise FreeSurfer colour-table names (``FreeSurferColorLUT.txt`` from ``$FREESURFER_HOME``
or beside the label map when present, else the built-in ``aseg`` subset below).
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

import numpy as np
from scipy import ndimage

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


FACES = ndimage.generate_binary_structure(3, 1)  # face (6-) connectivity
# Largest parts (voxels) removed as thin noise or filled as dents, tried in turn (None: any).
# 0 first: a clean label at a coarse grid keeps its one-voxel caps (an ellipsoid of 7-12 mm
# semi-axes on 2 mm voxels lost 2.8 % of its volume when parts of 2 voxels were removed).
NOISE_SIZES = (0, 8, 27, 64, 216, None)


def _largest_component(mask: np.ndarray) -> tuple[np.ndarray, int, int]:
    """The largest face-connected piece, the number of other pieces and their voxels."""
    labels, n = ndimage.label(mask, FACES)
    if n <= 1:
        return mask, 0, 0
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    keep = int(np.argmax(sizes))
    return labels == keep, n - 1, int(sizes.sum() - sizes[keep])


def _small_parts(change: np.ndarray, max_voxels: int | None) -> np.ndarray:
    """The voxels of ``change`` in 26-connected parts of at most ``max_voxels`` (None: all)."""
    if max_voxels is None:
        return change
    if max_voxels == 0:
        return np.zeros_like(change)
    labels, n = ndimage.label(change, np.ones((3, 3, 3), bool))
    if n == 0:
        return change
    small = np.bincount(labels.ravel()) <= max_voxels
    small[0] = False
    return small[labels]


def critical_voxels(mask: np.ndarray) -> np.ndarray:
    """Voxels of the critical configurations of a binary image (Latecki 1997), where the
    boundary between the two values is not a 2-manifold: the four voxels of every 2x2 square
    around an edge with a diagonal pattern, and the eight of every 2x2x2 cube in which two
    antipodal voxels alone have one value."""
    m = np.asarray(mask, bool)
    out = np.zeros_like(m)

    def part(offset) -> tuple:
        return tuple(slice(o, n - 1 + o) if o is not None else slice(None)
                     for o, n in zip(offset, m.shape))

    for axis in range(3):  # squares around the edges along ``axis``
        a, b = [d for d in range(3) if d != axis]
        offs = []
        for da, db in ((0, 0), (1, 0), (0, 1), (1, 1)):
            corner: list[int | None] = [None, None, None]
            corner[a], corner[b] = da, db
            offs.append(part(corner))
        p00, p10, p01, p11 = (m[o] for o in offs)
        crit = (p00 == p11) & (p10 == p01) & (p00 != p10)
        for o in offs:
            out[o] |= crit
    cube: list[tuple[int, ...]] = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    values = {c: m[part(c)] for c in cube}
    for c in cube[:4]:  # the four antipodal pairs
        opposite = tuple(1 - x for x in c)
        alone = values[c] == values[opposite]
        for other in cube:
            if other not in (c, opposite):
                alone &= values[other] != values[c]
        for other in cube:
            out[part(other)] |= alone
    return out


def cubical_genus(mask: np.ndarray) -> int:
    """Genus of the boundary of a well-composed, face-connected mask with no cavity, from
    the Euler characteristic of its union of closed voxel cubes (V - E + F - C = 1 - genus)."""
    m = np.pad(np.asarray(mask, bool), 1)
    count = 0
    for dims in range(4):  # cells of dimension 3 - dims: voxels, faces, edges, vertices
        for axes in itertools.combinations(range(3), dims):
            cell = m.copy()
            for axis in axes:  # a cell exists when a voxel on either side along ``axis`` does
                cell = cell[(slice(None),) * axis + (slice(1, None),)] | \
                    cell[(slice(None),) * axis + (slice(None, -1),)]
            count += (-1) ** (3 - dims) * int(cell.sum())
    return 1 - count


def well_composed(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """The mask with its critical squares and cubes (:func:`critical_voxels`) filled, round
    after round until none is left, enclosed cavities filled too; and the voxels added."""
    solid, added = np.asarray(mask, bool), 0
    for _ in range(100):  # filling only adds voxels: a few rounds in practice
        fix = critical_voxels(solid) & ~solid
        if not fix.any():
            break
        added += int(fix.sum())
        solid = ndimage.binary_fill_holes(solid | fix, FACES)
    return solid, added


def noise_element(spacing=None) -> np.ndarray:
    """The 1-voxel structuring element of the opening and closing that tell noise handles:
    the face cross over the axes whose spacing is within 1.5 times the finest (on 0.5 x 0.5
    x 2 mm voxels, in-plane only: a 2 mm step is no one-voxel noise there)."""
    element = FACES.copy()
    if spacing is not None:
        spacing = np.asarray(spacing, dtype=np.float64)
        for axis in np.flatnonzero(spacing > 1.5 * spacing.min()):
            index = [1, 1, 1]
            for end in (0, 2):
                index[axis] = end
                element[tuple(index)] = False
    return element


def repair_mask(mask: np.ndarray, spacing=None) -> tuple[np.ndarray, dict]:
    """One face-connected, well-composed solid from a manual label's mask (module docstring,
    step 2) and what was changed: ``islands`` and ``island_voxels`` dropped,
    ``thin_voxels_removed``, ``dent_voxels_filled``, ``cavity_voxels_filled``,
    ``contact_voxels_filled`` (edge/corner contacts resolved), ``noise_size`` (the largest
    part treated as noise, voxels; None: any) and ``genus``. Empty when nothing solid is left.
    ``spacing`` (mm per axis) shapes the opening and closing (:func:`noise_element`)."""
    m = np.pad(np.asarray(mask, bool), 2)
    m, islands, island_voxels = _largest_component(m)
    element = noise_element(spacing)
    opened = ndimage.binary_opening(m, element)
    target, best = None, None
    for size in NOISE_SIZES:
        removed = _small_parts(m & ~opened, size)
        cut, more, more_voxels = _largest_component(m & ~removed)
        added = _small_parts(ndimage.binary_closing(cut, element) & ~cut, size)
        solid = cut | added
        filled = ndimage.binary_fill_holes(solid, FACES)
        info = {"islands": islands + more, "island_voxels": island_voxels + more_voxels,
                "thin_voxels_removed": int(removed.sum()), "dent_voxels_filled": int(added.sum()),
                "cavity_voxels_filled": int((filled & ~solid).sum()), "noise_size": size}
        solid, info["contact_voxels_filled"] = well_composed(filled)
        if not solid.any():
            break
        genus = info["genus"] = cubical_genus(solid)
        if best is None:
            # the genus a 1-voxel opening and closing of the whole label keeps
            smooth, _, _ = _largest_component(ndimage.binary_closing(opened, element))
            smooth, _ = well_composed(ndimage.binary_fill_holes(smooth, FACES))
            target = cubical_genus(smooth) if smooth.any() else None
        best = (solid, info)
        if target is None or genus <= target:
            break
    if best is None:  # thinner than two voxels everywhere: the piece as it is, made well-composed
        solid, contacts = well_composed(ndimage.binary_fill_holes(m, FACES))
        best = (solid, {"islands": islands, "island_voxels": island_voxels,
                        "thin_voxels_removed": 0, "dent_voxels_filled": 0,
                        "cavity_voxels_filled": 0, "contact_voxels_filled": contacts,
                        "noise_size": 0, "genus": cubical_genus(solid) if solid.any() else None})
    solid, info = best
    return solid[2:-2, 2:-2, 2:-2], info


def vtk_image(values: np.ndarray):
    """A vtkImageData of a 3-D array (index order i, j, k), unit spacing at the origin."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData

    image = vtkImageData()
    image.SetDimensions(*values.shape)
    image.GetPointData().SetScalars(numpy_to_vtk(np.asarray(values).ravel(order="F"), deep=True))
    return image


def polydata_arrays(poly) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float, faces (F, 3) int) of a triangle vtkPolyData."""
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
    nets.SetInputData(vtk_image(padded))
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
    v, f = polydata_arrays(smoother.GetOutput())
    v = (v - 1.0) @ np.asarray(affine)[:3, :3].T + np.asarray(affine)[:3, 3]
    if len(f) and meshops.volume(v, f) < 0:
        f = f[:, ::-1].copy()
    return v, f


def label_surface(volume: Volume, value: int, *, n_vertices: int | None = 2000,
                  name: str = "", source: str = "label map", info: dict | None = None,
                  label_name: str | None = None) -> TriMesh:
    """One label of a label map as a closed surface in world RAS mm (module docstring).

    ``n_vertices`` None keeps the Surface Nets resolution (about one vertex per boundary
    voxel face). ``info`` (if given) gets ``voxels`` and what :func:`repair_mask` changed
    (``islands`` dropped and their ``island_voxels``, ...), ``genus`` and the surface's
    topology check. Raises :class:`LabelError` naming ``source`` and the label when the
    label has no voxel or no closed 2-manifold surface can be made of it.
    """
    from core.correspondence.grooming import remesh

    data = np.asarray(volume.data)
    mask = data == value
    what = f"{source}: label {label_name or value} (value {value})"
    if not mask.any():
        present = np.unique(data)
        shown = ", ".join(str(int(p)) for p in present[:20]) + (" ..." if len(present) > 20 else "")
        raise LabelError(f"{what} has no voxel (values present: {shown})")
    # Bounding box from the three axis projections (argwhere would list every voxel).
    spans = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
             for axis in range(3)]
    lo = np.maximum([s[0] - 1 for s in spans], 0)
    hi = np.minimum([s[-1] + 2 for s in spans], mask.shape)
    crop = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    shift = np.eye(4)
    shift[:3, 3] = lo
    solid, repaired = repair_mask(crop, np.linalg.norm(np.asarray(volume.affine)[:3, :3], axis=0))
    if not solid.any():
        raise LabelError(f"{what} has no solid region")
    v, f = mask_surface(solid, np.asarray(volume.affine) @ shift)
    if n_vertices is not None and len(v) >= 4:
        v, f = remesh(v, f, int(n_vertices))
    check = meshops.topology(f, len(v))
    if info is not None:
        n_voxels = int(np.count_nonzero(crop))
        info.update(voxels=n_voxels, **repaired, dropped_pieces=int(repaired["islands"]),
                    dropped_voxel_share=repaired["island_voxels"] / max(n_voxels, 1),
                    topology=check)
    if check["genus"] is None or check["genus"] != repaired["genus"]:
        raise LabelError(f"{what}: no closed 2-manifold surface could be made of it "
                         f"({_topology_text(check)}, label genus {repaired['genus']})")
    return TriMesh(v, f, name or f"label_{value}")


def repair_note(info: dict) -> str:
    """What :func:`repair_mask` changed, as ", ..." for a one-line report ("" for nothing)."""
    done = []
    if info.get("islands"):
        done.append(f"{info['islands']} island(s) dropped ({info['island_voxels']} voxels)")
    for key, text in (("thin_voxels_removed", "thin voxels removed"),
                      ("dent_voxels_filled", "dent voxels filled"),
                      ("cavity_voxels_filled", "cavity voxels filled"),
                      ("contact_voxels_filled", "voxels added at edge/corner contacts")):
        if info.get(key):
            done.append(f"{info[key]} {text}")
    return "".join(", " + d for d in done)


def _topology_text(check: dict) -> str:
    parts = [f"{check[k]} {k.replace('_', ' ')}" for k in
             ("open_edges", "non_manifold_edges", "non_manifold_vertices", "misoriented_edges")
             if check[k]]
    if check["pieces"] != 1:
        parts.append(f"{check['pieces']} pieces")
    return ", ".join(parts) or f"genus {check['genus']}"


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

    out: list[tuple[str, TriMesh | None, str | None]] = []
    for i, path in enumerate(paths):
        report(progress, i / max(len(paths), 1), f"meshing {Path(path).name}")
        try:
            out.append((str(path), label_map_surface(path, label, n_vertices=n_vertices), None))
        except (ValueError, OSError) as exc:
            out.append((str(path), None, " ".join(str(exc).split())))
    report(progress, 1.0, "meshed")
    return out
