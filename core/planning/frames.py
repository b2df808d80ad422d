"""Stereotactic planning geometry: the AC-PC frame, trajectories and their surface crossings.

Deep brain stimulation planning systems give positions relative to the mid-commissural point
(MCP, midway between the anterior and posterior commissures, AC and PC) in a frame whose
anterior axis runs along the AC-PC line and whose vertical axis lies in the midsagittal plane
(Talairach & Tournoux's convention, used by frame-based and frameless planning alike):

- origin: MCP = (AC + PC) / 2;
- anterior axis y: from PC to AC;
- vertical axis z: the component of (midline point - MCP) orthogonal to y, i.e. the
  midsagittal plane is spanned by y and z and contains the midline point;
- lateral axis x = y x z, pointing to the patient's right (so the frame is RAS-like and
  right-handed: a point in the right hemisphere has positive lateral coordinate).

A trajectory runs from an entry point (scalp side) to a target. Its orientation in the AC-PC
frame is given by the two angles of frame-based planning (Leksell convention), computed from
the unit direction d = (entry - target) / |entry - target| expressed in the AC-PC frame:

- ``ring_deg``: angle in the sagittal (y, z) plane between the anterior axis and the
  trajectory's projection, atan2(d_z, d_y): 90 degrees is a vertical trajectory, less than 90
  tilts the entry anteriorly (the usual case), more than 90 posteriorly;
- ``arc_deg``: angle in the coronal (x, z) plane between the patient's right axis and the
  trajectory's projection, atan2(d_z, d_x): 90 degrees is parallel to the midsagittal plane,
  less than 90 puts the entry to the right of the target, more than 90 to the left.

Also reported: ``midsagittal_angle_deg``, the angle between the trajectory and the
midsagittal plane in 3D (0 = parallel to it), as frameless systems show it.

Crossings of a trajectory with a closed triangle surface are found exactly (vectorised
Moeller-Trumbore ray/triangle intersection); whether each crossing enters or leaves follows
from the sign of the triangle normal against the direction (outward, consistently oriented
normals, as every surface SSM Studio builds has).

Warnings (:func:`trajectory_warnings`), what a neurosurgeon checks before accepting a plan:
the target outside its own structure (with its distance to the surface), the path from the
entry to the target crossing another structure or the ventricles (where it enters and
leaves), or passing closer than a margin to one (the closest approach along the path, from
the exact signed distance of points every ``step_mm`` along it, :func:`path_distances`).
The ventricles are the demo template's (``resources/ventricles_mni09a.vtk``, derived from its
tissue maps by ``resources/make_demo.py``), placed on the image as the library models are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core import RESOURCES_DIR
from core.geometry.mesh import volume as mesh_volume
from core.geometry.toolkit import closest_points_on_surface, signed_surface_distance

#: AC and PC closer than this (mm) are refused: in adults they are ~23-28 mm apart.
MIN_AC_PC_MM = 5.0
#: The midline point must lie at least this far (mm) from the AC-PC line.
MIN_MIDLINE_OFFSET_MM = 5.0
#: A path passing closer than this (mm) to a structure it does not cross is warned about.
PATH_MARGIN_MM = 2.0
#: The demo template's ventricles (make_demo.py), template world RAS mm.
VENTRICLES_FILE = RESOURCES_DIR / "ventricles_mni09a.vtk"
VENTRICLES_NAME = "ventricles"


class PlanningError(ValueError):
    """A planning input the user must correct (e.g. AC equal to PC)."""


def _point(value, name: str) -> np.ndarray:
    p = np.asarray(value, dtype=np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise PlanningError(f"{name} must be three finite coordinates (mm), got {value!r}")
    return p


@dataclass(frozen=True)
class ACPCFrame:
    """The AC-PC coordinate frame, from three world points (RAS mm).

    ``rotation`` (3, 3) has the frame's axes (lateral, anterior, vertical) as rows, so that
    ``rotation @ (p - origin)`` gives a world point's AC-PC coordinates.
    """

    ac: np.ndarray
    pc: np.ndarray
    midline: np.ndarray
    origin: np.ndarray
    rotation: np.ndarray

    @classmethod
    def from_points(cls, ac, pc, midline) -> ACPCFrame:
        """Build the frame; raises :class:`PlanningError` for degenerate input."""
        ac, pc, midline = _point(ac, "AC"), _point(pc, "PC"), _point(midline, "midline point")
        along = ac - pc
        length = float(np.linalg.norm(along))
        if length < MIN_AC_PC_MM:
            raise PlanningError(
                f"AC and PC are {length:.1f} mm apart; set them on the two commissures "
                f"(at least {MIN_AC_PC_MM:g} mm apart, typically 23-28 mm)")
        y = along / length
        origin = (ac + pc) / 2.0
        up = midline - origin
        up = up - np.dot(up, y) * y
        offset = float(np.linalg.norm(up))
        if offset < MIN_MIDLINE_OFFSET_MM:
            raise PlanningError(
                f"the midline point is {offset:.1f} mm from the AC-PC line; place it in the "
                f"midsagittal plane, above the commissures (at least {MIN_MIDLINE_OFFSET_MM:g} mm "
                "away from the line)")
        z = up / offset
        x = np.cross(y, z)
        return cls(ac, pc, midline, origin, np.stack([x, y, z]))

    def to_acpc(self, points) -> np.ndarray:
        """World RAS (..., 3) -> AC-PC (lateral, anterior, vertical) mm, same shape."""
        p = np.asarray(points, dtype=np.float64)
        return (p - self.origin) @ self.rotation.T

    def to_world(self, points) -> np.ndarray:
        """AC-PC (..., 3) -> world RAS mm."""
        p = np.asarray(points, dtype=np.float64)
        return p @ self.rotation + self.origin

    def directions_to_acpc(self, vectors) -> np.ndarray:
        """World direction vectors (..., 3) -> AC-PC frame (no translation)."""
        return np.asarray(vectors, dtype=np.float64) @ self.rotation.T

    @property
    def ac_pc_distance(self) -> float:
        return float(np.linalg.norm(self.ac - self.pc))

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous world -> AC-PC transform (column vectors)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = -self.rotation @ self.origin
        return m


def format_acpc(coords) -> str:
    """One-line readout of AC-PC coordinates: 'AC-PC: lat +12.0 (R)  AP -3.0  vert -4.0 mm'."""
    x, y, z = (float(c) for c in np.asarray(coords).reshape(3))
    side = "R" if x > 0 else ("L" if x < 0 else "mid")
    return f"AC-PC: lat {x:+.1f} ({side})  AP {y:+.1f}  vert {z:+.1f} mm"


@dataclass(frozen=True)
class Crossing:
    """Where a trajectory meets a surface: distance from the entry (mm) and direction."""

    distance: float
    entering: bool
    point: np.ndarray


def ray_surface_crossings(origin, direction, vertices: np.ndarray, faces: np.ndarray,
                          max_distance: float | None = None) -> list[Crossing]:
    """All crossings of the ray origin + t * direction (t >= 0, t <= max_distance) with a mesh.

    ``direction`` need not be unit; distances are in mm along the unit direction. Sorted by
    distance; duplicate hits on a shared edge (within 1e-9 mm) are merged.
    """
    o = _point(origin, "ray origin")
    d = _point(direction, "ray direction")
    norm = float(np.linalg.norm(d))
    if norm == 0.0:
        raise PlanningError("entry and target coincide: the trajectory has no direction")
    d = d / norm
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    pvec = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, pvec)
    ok = np.abs(det) > 1e-14
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    tvec = o - a
    u = np.einsum("ij,ij->i", tvec, pvec) * inv
    qvec = np.cross(tvec, e1)
    w = (qvec @ d) * inv
    t = np.einsum("ij,ij->i", e2, qvec) * inv
    eps = 1e-12
    hit = ok & (u >= -eps) & (w >= -eps) & (u + w <= 1 + eps) & (t >= 0)
    if max_distance is not None:
        hit &= t <= max_distance
    idx = np.flatnonzero(hit)
    order = idx[np.argsort(t[idx])]
    normals = np.cross(e1[order], e2[order])
    entering = normals @ d < 0
    out: list[Crossing] = []
    for k, i in enumerate(order):
        if out and abs(t[i] - out[-1].distance) < 1e-9 and entering[k] == out[-1].entering:
            continue
        out.append(Crossing(float(t[i]), bool(entering[k]), o + t[i] * d))
    return out


@dataclass(frozen=True)
class Trajectory:
    """A straight trajectory from ``entry`` to ``target`` (world RAS mm)."""

    entry: np.ndarray
    target: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "entry", _point(self.entry, "entry point"))
        object.__setattr__(self, "target", _point(self.target, "target point"))
        if self.length < 1e-6:
            raise PlanningError("entry and target coincide: the trajectory has no direction")

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.target - self.entry))

    @property
    def direction(self) -> np.ndarray:
        """Unit vector from entry to target."""
        return (self.target - self.entry) / self.length

    def point_at(self, depth: float) -> np.ndarray:
        """World point at ``depth`` mm from the entry along the trajectory."""
        return self.entry + float(depth) * self.direction

    def angles(self, frame: ACPCFrame) -> dict[str, float]:
        """Ring and arc angles (Leksell convention) and the angle to the midsagittal plane, degrees."""
        up = frame.directions_to_acpc(-self.direction)  # target -> entry, in the AC-PC frame
        x, y, z = up
        ring = float(np.degrees(np.arctan2(z, y)))
        arc = float(np.degrees(np.arctan2(z, x)))
        midsagittal = float(np.degrees(np.arcsin(min(1.0, abs(float(x))))))
        return {"ring_deg": ring, "arc_deg": arc, "midsagittal_angle_deg": midsagittal}

    def crossings(self, vertices: np.ndarray, faces: np.ndarray) -> list[Crossing]:
        """Crossings with a closed surface between the entry and the target."""
        return ray_surface_crossings(self.entry, self.direction, vertices, faces,
                                     max_distance=self.length)

    def segments_inside(self, vertices: np.ndarray, faces: np.ndarray,
                        extend: float = 0.0) -> list[tuple[float, float]]:
        """(enter, leave) depths (mm from the entry) where the trajectory is inside the surface.

        ``extend`` mm beyond the target are also searched (a lead goes past its target). A
        trajectory that ends inside the surface gives a last interval ending at the search end.
        """
        end = self.length + max(0.0, float(extend))
        hits = ray_surface_crossings(self.entry, self.direction, vertices, faces, end)
        intervals: list[tuple[float, float]] = []
        start = 0.0 if (hits and not hits[0].entering) else None
        for h in hits:
            if h.entering and start is None:
                start = h.distance
            elif not h.entering and start is not None:
                intervals.append((start, h.distance))
                start = None
        if start is not None:
            intervals.append((start, end))
        return intervals


def volume_centroid(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centroid of the solid bounded by a closed, outward-oriented surface (mm).

    Sum over the tetrahedra (origin, a, b, c) of their signed volume times their centroid,
    divided by the total volume; exact for any closed polyhedron.
    """
    v = np.asarray(vertices, dtype=np.float64)
    shift = v.mean(axis=0)  # for round-off far from the origin (scanner coordinates)
    t = v[np.asarray(faces, dtype=np.int64)] - shift
    vol = np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])) / 6.0
    total = vol.sum()
    if abs(total) < 1e-12:
        raise PlanningError("the surface encloses no volume (open or degenerate mesh)")
    centroids = t.sum(axis=1) / 4.0
    return (vol[:, None] * centroids).sum(axis=0) / total + shift


def structure_row(name: str, vertices: np.ndarray, faces: np.ndarray,
                  frame: ACPCFrame | None = None) -> dict:
    """One row of the structure table: volume (mm^3), centroid in world and AC-PC."""
    centroid = volume_centroid(vertices, faces)
    row = {"name": name, "volume_mm3": abs(mesh_volume(vertices, faces)),
           "centroid_world": centroid.tolist()}
    if frame is not None:
        row["centroid_acpc"] = frame.to_acpc(centroid).tolist()
    return row


def anchored_point_weights(vertices: np.ndarray, point, k: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Express a point as a weighted combination of its ``k`` nearest vertices.

    Returns (indices (k,), weights (k,), summing to 1) such that ``weights @ vertices[indices]``
    equals ``point`` as closely as a convex combination of those vertices allows (least squares
    on the affine combination, inverse-distance weights as fallback), so that the point moves
    with the surface when the shape deforms (a target defined in the model's frame).
    """
    v = np.asarray(vertices, dtype=np.float64)
    p = _point(point, "anchored point")
    k = int(min(max(k, 4), len(v)))
    dist = np.linalg.norm(v - p, axis=1)
    idx = np.argsort(dist)[:k]
    # affine combination: minimise |sum w_i v_i - p|^2 + tiny ridge, subject to sum w_i = 1
    a = np.vstack([(v[idx] - p).T, np.ones(k)])
    rhs = np.concatenate([np.zeros(3), [1.0]])
    ridge = 1e-6 * np.eye(k)
    w = np.linalg.solve(a.T @ a + ridge, a.T @ rhs)
    if not np.all(np.isfinite(w)):
        inv = 1.0 / np.maximum(dist[idx], 1e-9)
        w = inv / inv.sum()
    return idx, w / w.sum()


def anchored_point(vertices: np.ndarray, indices: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The point anchored by :func:`anchored_point_weights` on (possibly deformed) vertices."""
    return np.asarray(weights) @ np.asarray(vertices, dtype=np.float64)[np.asarray(indices)]


def path_distances(trajectory: Trajectory, structures, step_mm: float = 0.5) -> list[dict]:
    """Per structure (objects with ``name``, ``vertices``, ``faces``), from the entry to the
    target: the closest approach of the path (signed: negative when the path is inside), the
    depth where it happens, and the (enter, leave) depths where the path is inside."""
    n = max(2, int(np.ceil(trajectory.length / float(step_mm))) + 1)
    depths = np.linspace(0.0, trajectory.length, n)
    samples = trajectory.entry + depths[:, None] * trajectory.direction
    rows = []
    for s in structures:
        # the sign from the path's exact inside intervals (cheaper than winding numbers)
        inside = trajectory.segments_inside(s.vertices, s.faces)
        _, d = closest_points_on_surface(samples, s.vertices, s.faces)
        within = np.zeros(len(depths), bool)
        for a, b in inside:
            within |= (depths >= a) & (depths <= b)
        d = np.where(within, -d, d)
        k = int(np.argmin(d))
        rows.append({"structure": s.name, "min_distance_mm": float(d[k]),
                     "at_depth_mm": float(depths[k]), "inside": [list(iv) for iv in inside]})
    return rows


def trajectory_warnings(trajectory: Trajectory, target_structure, structures, *,
                        margin_mm: float = PATH_MARGIN_MM, step_mm: float = 0.5) -> list[dict]:
    """Warnings of one trajectory (module docstring), each ``{"kind", "structure", ...,
    "message"}``: ``target_outside`` (the target outside ``target_structure``, its distance),
    ``crosses`` / ``crosses_ventricle`` (the path from entry to target goes through another
    structure / the ventricles: enter and leave depths from the entry), ``passes_near`` (closer
    than ``margin_mm`` without crossing). ``target_structure`` is the trajectory's own structure
    (or None); ``structures`` every surface to check (the ventricles named
    :data:`VENTRICLES_NAME`)."""
    out: list[dict] = []
    if target_structure is not None:
        d = float(signed_surface_distance(trajectory.target, target_structure.vertices,
                                          target_structure.faces)[0])
        if d > 0:
            out.append({"kind": "target_outside", "structure": target_structure.name,
                        "distance_mm": d,
                        "message": f"the target lies {d:.1f} mm outside {target_structure.name}"})
    others = [s for s in structures if target_structure is None or s.name != target_structure.name]
    for row in path_distances(trajectory, others, step_mm):
        name = row["structure"]
        ventricle = VENTRICLES_NAME in name.lower()
        inside = [iv for iv in row["inside"] if iv[1] - iv[0] > 1e-6]
        if inside:
            a, b = inside[0]
            where = ", ".join(f"{x:.1f}-{y:.1f} mm" for x, y in inside)
            out.append({"kind": "crosses_ventricle" if ventricle else "crosses", "structure": name,
                        "enter_mm": a, "leave_mm": b, "intervals_mm": inside,
                        "message": f"the trajectory crosses {'the ' if ventricle else ''}{name} "
                                   f"at {where} from the entry"})
        elif row["min_distance_mm"] < margin_mm:
            out.append({"kind": "passes_near", "structure": name,
                        "distance_mm": row["min_distance_mm"], "at_depth_mm": row["at_depth_mm"],
                        "message": f"the trajectory passes {row['min_distance_mm']:.1f} mm from "
                                   f"{name} (at {row['at_depth_mm']:.1f} mm from the entry)"})
    return out


@dataclass(frozen=True)
class Surface:
    """A named closed surface (world RAS mm): what the warnings and read-outs take."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray


def template_ventricles(template_to_image: np.ndarray | None = None) -> Surface:
    """The demo template's ventricles, mapped by ``template_to_image`` (4x4, template world ->
    image world; None: left in template space)."""
    from core.io import load_mesh

    mesh = load_mesh(VENTRICLES_FILE)
    v = mesh.vertices
    if template_to_image is not None:
        t = np.asarray(template_to_image, dtype=np.float64)
        v = v @ t[:3, :3].T + t[:3, 3]
    return Surface(VENTRICLES_NAME, v, mesh.faces)
