"""A DBS lead on a planned trajectory: its contacts, where they sit and in which structure.

Lead geometry as clinicians pick a lead (the manufacturers' published dimensions; nominal,
check the lead's own data sheet before clinical use): ``levels`` contacts along the lead from
the tip up, each level a ring (1) or split into directional segments (3, each spanning about
a third of the circumference); every contact ``contact_length_mm`` long, consecutive levels
``spacing_mm`` apart edge to edge, the lowest level's distal edge ``tip_offset_mm`` above the
lead's tip.

- Medtronic 3389 and 3387: 4 rings of 1.5 mm, 0.5 mm and 1.5 mm apart, 1.27 mm diameter
  (Medtronic DBS lead models 3387/3389 specifications).
- Boston Scientific Vercise Cartesia directional: 1-3-3-1 (8 contacts), 1.5 mm contacts,
  0.5 mm apart, 1.3 mm diameter.
- Boston Scientific Vercise (standard): 8 rings of 1.5 mm, 0.5 mm apart, 1.3 mm diameter.

The lead lies on the trajectory (entry -> target); ``depth_mm`` moves its tip along the
trajectory from the target (positive: deeper, past the target; negative: short of it). The
directional segments' orientation is measured about the lead's axis from the direction
anterior in the image (world +A projected onto the plane normal to the lead), turning towards
the patient's left (segment "a" at 0 degrees, then 120 and 240 degrees).

Read-outs per contact (:func:`contact_readout`): the centre in world RAS, AC-PC
(``core.planning.frames.ACPCFrame``) and image voxel coordinates, and the signed distance to each
fitted structure (exact closest point, sign from the winding number,
``core.geometry.toolkit.signed_surface_distance``): the contact lies in the structure of the most
negative distance, else it is outside every structure and the nearest one is named.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.geometry.toolkit import signed_surface_distance
from core.planning.frames import ACPCFrame, PlanningError, Trajectory


@dataclass(frozen=True)
class LeadType:
    """A DBS lead's contact layout (mm)."""

    key: str                       # command-line name: "medtronic-3389"
    name: str                      # shown: "Medtronic 3389"
    levels: tuple[int, ...]        # contacts per level from the tip up: 1 ring, 3 directional
    contact_length_mm: float
    spacing_mm: float              # gap between consecutive levels (edge to edge)
    diameter_mm: float
    tip_offset_mm: float           # lead tip -> distal edge of the lowest level
    first_number: int = 0          # the manufacturer's number of the lowest contact

    @property
    def n_contacts(self) -> int:
        return int(sum(self.levels))

    @property
    def span_mm(self) -> float:
        """From the lowest contact's distal edge to the highest's proximal edge."""
        n = len(self.levels)
        return n * self.contact_length_mm + (n - 1) * self.spacing_mm

    def level_centres_mm(self) -> np.ndarray:
        """Distance (L,) of each level's centre from the lead's tip, along the lead."""
        pitch = self.contact_length_mm + self.spacing_mm
        return self.tip_offset_mm + self.contact_length_mm / 2 + pitch * np.arange(len(self.levels))


LEAD_TYPES: dict[str, LeadType] = {lead.key: lead for lead in (
    LeadType("medtronic-3389", "Medtronic 3389", (1, 1, 1, 1), 1.5, 0.5, 1.27, 1.5, 0),
    LeadType("medtronic-3387", "Medtronic 3387", (1, 1, 1, 1), 1.5, 1.5, 1.27, 1.5, 0),
    LeadType("boston-cartesia-directional", "Boston Scientific Vercise Cartesia directional",
             (1, 3, 3, 1), 1.5, 0.5, 1.3, 1.0, 1),
    LeadType("boston-vercise", "Boston Scientific Vercise", (1,) * 8, 1.5, 0.5, 1.3, 1.1, 1),
)}


def lead_type(key: str) -> LeadType:
    """The lead type named ``key`` (one line naming the known ones if unknown)."""
    try:
        return LEAD_TYPES[key]
    except KeyError:
        raise PlanningError(f"unknown lead type {key!r}; known: {', '.join(LEAD_TYPES)}") from None


@dataclass(frozen=True)
class Contact:
    """One contact of a placed lead (world RAS mm)."""

    name: str                      # "0".."3" (Medtronic) / "1", "2a", "2b", ... (Boston)
    level: int
    centre: np.ndarray             # ring: on the axis; segment: on the lead's surface
    axis_point: np.ndarray         # the level's centre on the lead's axis
    angle_deg: float | None = None  # directional segments: orientation about the axis


@dataclass(frozen=True)
class PlacedLead:
    """A lead type on a trajectory: tip, axis (tip -> entry) and contacts, world RAS mm."""

    lead: LeadType
    tip: np.ndarray
    axis: np.ndarray               # unit, from the tip towards the entry
    depth_mm: float
    rotation_deg: float
    contacts: tuple[Contact, ...]


def contact_extents(placed: PlacedLead) -> list[dict]:
    """What a view draws of each contact: its name, the two ends of its band on the lead's
    axis (world RAS mm, distal first), the lead's radius, and for a directional segment the
    centre angle and the arc it spans (degrees; a third of the circle minus the insulating
    gaps, drawn at a nominal 90 degrees: check the lead's data sheet)."""
    half = placed.lead.contact_length_mm / 2
    out = []
    for c in placed.contacts:
        row = {"name": c.name, "start": c.axis_point - half * placed.axis,
               "end": c.axis_point + half * placed.axis, "radius_mm": placed.lead.diameter_mm / 2,
               "length_mm": placed.lead.contact_length_mm}
        if c.angle_deg is not None:
            row.update(angle_deg=c.angle_deg, arc_deg=90.0)
        out.append(row)
    return out


def across_in_plane(placed: PlacedLead, normal: np.ndarray,
                    fallback: np.ndarray) -> np.ndarray:
    """The unit direction across the lead within a slice of normal ``normal`` (where a view
    draws the band's width); ``fallback`` (a unit in-plane direction) when the lead runs along
    the normal."""
    across = np.cross(np.asarray(normal, dtype=np.float64), placed.axis)
    size = float(np.linalg.norm(across))
    if size < 1e-6:
        return np.asarray(fallback, dtype=np.float64)
    return across / size


def place_lead(trajectory: Trajectory, lead: LeadType | str, depth_mm: float = 0.0,
               rotation_deg: float = 0.0) -> PlacedLead:
    """Put ``lead`` on ``trajectory``: tip at the target moved ``depth_mm`` along the
    trajectory (positive deeper), directional segments turned by ``rotation_deg``."""
    lead = lead_type(lead) if isinstance(lead, str) else lead
    depth = float(depth_mm)
    if not np.isfinite(depth):
        raise PlanningError(f"lead depth must be a finite number of mm, got {depth_mm!r}")
    forward = trajectory.direction
    tip = trajectory.target + depth * forward
    axis = -forward
    # Reference for the segments: image anterior projected onto the plane normal to the lead
    # (world left if the lead runs along A-P).
    ref = np.array([0.0, 1.0, 0.0]) - axis[1] * axis
    if np.linalg.norm(ref) < 1e-6:
        ref = np.array([-1.0, 0.0, 0.0]) - axis[0] * axis
    ref /= np.linalg.norm(ref)
    side = np.cross(axis, ref)    # ref turned by +90 degrees about the axis (towards the left)
    contacts = []
    number = lead.first_number
    for level, (count, along) in enumerate(zip(lead.levels, lead.level_centres_mm())):
        on_axis = tip + along * axis
        if count == 1:
            contacts.append(Contact(str(number), level, on_axis, on_axis))
            number += 1
            continue
        for k in range(count):
            angle = float(rotation_deg) + 360.0 * k / count
            radial = np.cos(np.radians(angle)) * ref + np.sin(np.radians(angle)) * side
            contacts.append(Contact(f"{number}{'abcdefgh'[k]}", level,
                                    on_axis + lead.diameter_mm / 2 * radial, on_axis,
                                    angle % 360.0))
        number += 1
    return PlacedLead(lead, tip, axis, depth, float(rotation_deg), tuple(contacts))


def contact_readout(placed: PlacedLead, structures, frame: ACPCFrame | None = None,
                    volume=None) -> list[dict]:
    """One JSON-ready row per contact: centre in world, AC-PC and voxel coordinates, the
    structure it lies in (or the nearest) and the signed distance to every structure.

    ``structures``: objects with ``name``, ``vertices`` and ``faces`` (fitted surfaces, world
    RAS); ``volume``: the image (``core.io.Volume``) for voxel coordinates.
    """
    centres = np.array([c.centre for c in placed.contacts])
    distances = {s.name: signed_surface_distance(centres, s.vertices, s.faces)
                 for s in structures}
    rows = []
    for i, c in enumerate(placed.contacts):
        row: dict = {"contact": c.name, "level": c.level, "world": c.centre.tolist()}
        if c.angle_deg is not None:
            row["angle_deg"] = c.angle_deg
        if frame is not None:
            row["acpc"] = frame.to_acpc(c.centre).tolist()
        if volume is not None:
            row["voxel"] = np.asarray(volume.world_to_voxel(c.centre), dtype=float).tolist()
        per = {name: float(d[i]) for name, d in distances.items()}
        row["signed_distance_mm"] = per
        if per:
            best = min(per, key=per.__getitem__)
            row["structure"] = best if per[best] < 0 else None
            row["nearest_structure"] = best
            row["distance_mm"] = per[best]
        else:
            row["structure"], row["nearest_structure"], row["distance_mm"] = None, None, None
        rows.append(row)
    return rows


def lead_report(placed: PlacedLead, structures, frame: ACPCFrame | None = None,
                volume=None) -> dict:
    """The lead's type, dimensions, tip and depth, and :func:`contact_readout`."""
    lead = placed.lead
    doc = {"type": lead.key, "name": lead.name, "levels": list(lead.levels),
           "contact_length_mm": lead.contact_length_mm, "spacing_mm": lead.spacing_mm,
           "diameter_mm": lead.diameter_mm, "tip_offset_mm": lead.tip_offset_mm,
           "depth_mm": placed.depth_mm, "rotation_deg": placed.rotation_deg,
           "tip_world": placed.tip.tolist(),
           "contacts": contact_readout(placed, structures, frame, volume)}
    if frame is not None:
        doc["tip_acpc"] = frame.to_acpc(placed.tip).tolist()
    return doc


def format_contact(row: dict) -> str:
    """One line of a contact read-out for the command line."""
    where = (f"in {row['structure']} ({row['distance_mm']:+.1f} mm)" if row.get("structure")
             else f"outside, nearest {row['nearest_structure']} at {row['distance_mm']:+.1f} mm"
             if row.get("nearest_structure") else "no structure")
    acpc = row.get("acpc")
    pos = (f"AC-PC ({acpc[0]:+.1f}, {acpc[1]:+.1f}, {acpc[2]:+.1f})" if acpc is not None else
           "world ({:.1f}, {:.1f}, {:.1f})".format(*row["world"]))
    return f"contact {row['contact']:>3}: {pos} mm, {where}"
