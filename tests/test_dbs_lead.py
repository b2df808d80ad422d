"""DBS leads on a trajectory, contact read-outs and plan warnings, on analytic spheres."""

from __future__ import annotations

import numpy as np
import pytest
from analytic import sphere as icosphere

from core.geometry.toolkit import signed_surface_distance, winding_numbers
from core.io import Volume
from core.planning.frames import ACPCFrame, PlanningError, Surface, Trajectory, trajectory_warnings
from core.planning.lead import LEAD_TYPES, contact_extents, contact_readout, lead_type, place_lead
from core.planning.report import LeadChoice, PlannedStructure, export_plan, plan_report

# A 6 mm sphere around the target, a 4 mm sphere on the way in, a 3 mm one beside the path.
TARGET = np.array([-12.0, -2.0, -4.0])
ENTRY = TARGET + [0.0, 0.0, 70.0]


def _spheres():
    va, fa = icosphere(6.0, TARGET, 4)
    vb, fb = icosphere(4.0, TARGET + [0, 0, 20.0], 4)
    vc, fc = icosphere(3.0, TARGET + [4.5, 0, 40.0], 4)
    return (Surface("target sphere", va, fa), Surface("sphere on the way", vb, fb),
            Surface("sphere beside", vc, fc))


def test_winding_number_and_signed_distance_of_a_sphere():
    v, f = icosphere(5.0, [1.0, 2.0, 3.0], 4)
    points = np.array([[1, 2, 3], [1, 2, 6.0], [1, 2, 9.0], [-5, 2, 3.0]])
    assert np.allclose(winding_numbers(points, v, f), [1, 1, 0, 0], atol=1e-9)
    # exact distances to a sphere of radius 5 (the icosphere's chord error is < 0.03 mm)
    d = signed_surface_distance(points, v, f)
    assert np.allclose(d, [-5.0, -2.0, 1.0, 1.0], atol=0.03)


def test_ring_lead_contacts_sit_at_the_published_pitch():
    traj = Trajectory(ENTRY, TARGET)
    for key, pitch in (("medtronic-3389", 2.0), ("medtronic-3387", 3.0)):
        placed = place_lead(traj, key)
        along = np.array([(c.centre - placed.tip) @ placed.axis for c in placed.contacts])
        # tip 1.5 mm below the lowest contact, 1.5 mm contacts: centres at 2.25 + k * pitch
        assert np.allclose(along, 2.25 + pitch * np.arange(4))
        assert [c.name for c in placed.contacts] == ["0", "1", "2", "3"]
        assert np.allclose(placed.tip, TARGET)
    deeper = place_lead(traj, "medtronic-3389", depth_mm=2.0)
    assert np.allclose(deeper.tip, TARGET + 2.0 * traj.direction)
    assert LEAD_TYPES["medtronic-3387"].span_mm == pytest.approx(10.5)
    assert LEAD_TYPES["medtronic-3389"].span_mm == pytest.approx(7.5)


def test_directional_lead_has_eight_contacts_120_degrees_apart_on_its_surface():
    lead = lead_type("boston-cartesia-directional")
    placed = place_lead(Trajectory(ENTRY, TARGET), lead, rotation_deg=30.0)
    names = [c.name for c in placed.contacts]
    assert names == ["1", "2a", "2b", "2c", "3a", "3b", "3c", "4"]
    segments = [c for c in placed.contacts if c.angle_deg is not None]
    radial = np.array([c.centre - c.axis_point for c in segments])
    assert np.allclose(np.linalg.norm(radial, axis=1), lead.diameter_mm / 2)
    assert np.allclose(radial @ placed.axis, 0.0, atol=1e-12)
    # a vertical lead: segment "a" at 30 degrees from anterior, turning to the left (-x)
    a = radial[0] / np.linalg.norm(radial[0])
    assert np.allclose(a, [-np.sin(np.radians(30)), np.cos(np.radians(30)), 0.0])
    cosines = radial[:3] @ radial[:3].T / (lead.diameter_mm / 2) ** 2
    assert np.allclose(cosines[np.triu_indices(3, 1)], -0.5)
    with pytest.raises(PlanningError, match="unknown lead type 'x'.*medtronic-3389"):
        lead_type("x")


def test_contacts_read_out_structure_distance_acpc_and_voxel():
    target_sphere, on_way, beside = _spheres()
    frame = ACPCFrame.from_points([0, 12, 0], [0, -12, 0], [0, 0, 40])
    volume = Volume(np.zeros((10, 10, 10), np.uint8),
                    np.array([[2.0, 0, 0, -50], [0, 2.0, 0, -40], [0, 0, 3.0, -30], [0, 0, 0, 1]]))
    placed = place_lead(Trajectory(ENTRY, TARGET), "medtronic-3387")
    rows = contact_readout(placed, [target_sphere, on_way, beside], frame, volume)
    for row, height in zip(rows, 2.25 + 3.0 * np.arange(4)):
        centre = TARGET + [0, 0, height]
        assert np.allclose(row["world"], centre)
        assert np.allclose(row["acpc"], frame.to_acpc(centre))
        assert np.allclose(row["voxel"], (centre - [-50, -40, -30]) / [2, 2, 3])
        assert row["signed_distance_mm"]["target sphere"] == pytest.approx(height - 6.0, abs=0.03)
    # contacts 0 and 1 (2.25, 5.25 mm) inside the 6 mm sphere, 2 and 3 outside it
    assert [r["structure"] for r in rows] == ["target sphere", "target sphere", None, None]
    assert rows[3]["nearest_structure"] == "sphere on the way"
    assert rows[3]["distance_mm"] == pytest.approx(20 - 11.25 - 4.0, abs=0.03)


def test_warnings_name_target_outside_crossing_and_grazing_with_distances():
    target_sphere, on_way, beside = _spheres()
    off_target = TARGET + [0.0, 8.0, 0.0]                  # 2 mm outside the 6 mm sphere
    traj = Trajectory(off_target + [0, 0, 70.0], off_target)
    warnings = {w["kind"]: w for w in trajectory_warnings(traj, target_sphere,
                                                         [target_sphere, on_way, beside])}
    assert warnings["target_outside"]["distance_mm"] == pytest.approx(2.0, abs=0.03)
    assert "2.0 mm outside target sphere" in warnings["target_outside"]["message"]
    assert "crosses" not in warnings                       # 8 mm off the 4 mm sphere's centre

    traj = Trajectory(ENTRY, TARGET)
    warnings = {w["kind"]: w for w in trajectory_warnings(traj, target_sphere,
                                                         [target_sphere, on_way, beside])}
    assert "target_outside" not in warnings
    crossing = warnings["crosses"]                          # enters at 70-24, leaves at 70-16
    assert crossing["structure"] == "sphere on the way"
    assert crossing["enter_mm"] == pytest.approx(46.0, abs=0.03)
    assert crossing["leave_mm"] == pytest.approx(54.0, abs=0.03)
    near = warnings["passes_near"]                          # 4.5 mm from the axis, radius 3
    assert near["structure"] == "sphere beside"
    assert near["distance_mm"] == pytest.approx(1.5, abs=0.02)
    assert near["at_depth_mm"] == pytest.approx(30.0, abs=0.5)


def test_ventricle_crossing_is_its_own_warning():
    target_sphere, _, _ = _spheres()
    v, f = icosphere(5.0, TARGET + [0, 0, 30.0], 4)
    kinds = [w["kind"] for w in trajectory_warnings(Trajectory(ENTRY, TARGET), target_sphere,
                                                     [target_sphere, Surface("ventricles", v, f)])]
    assert kinds == ["crosses_ventricle"]


def test_plan_report_carries_lead_and_warnings():
    target_sphere, on_way, beside = _spheres()
    a = PlannedStructure(target_sphere.name, target_sphere.vertices, target_sphere.faces,
                         target=TARGET, entry=ENTRY)
    b = PlannedStructure(on_way.name, on_way.vertices, on_way.faces)
    report = plan_report([a, b], None, lead=LeadChoice("medtronic-3389", depth_mm=1.0),
                         avoid=(beside,))
    traj = report["structures"][0]["trajectory"]
    assert traj["lead"]["type"] == "medtronic-3389"
    assert traj["lead"]["depth_mm"] == 1.0
    # 1 mm deeper: centres 1.25, 3.25, 5.25, 7.25 mm above the target, in a 6 mm sphere
    assert [c["structure"] for c in traj["lead"]["contacts"]] == ["target sphere"] * 3 + [None]
    assert {w["kind"] for w in report["warnings"]} == {"crosses", "passes_near"}
    assert {r["structure"] for r in traj["path_distances"]} == {"sphere on the way", "sphere beside"}


def test_export_plan_writes_the_contacts_table(tmp_path):
    import csv

    target_sphere, on_way, _ = _spheres()
    a = PlannedStructure(target_sphere.name, target_sphere.vertices, target_sphere.faces,
                         target=TARGET, entry=ENTRY)
    frame = ACPCFrame.from_points([0, 12, 0], [0, -12, 0], [0, 0, 40])
    written = export_plan(tmp_path, [a], None, frame, meshes=False,
                          lead=LeadChoice("boston-cartesia-directional"))
    assert tmp_path / "plan_contacts.csv" in written
    rows = list(csv.DictReader((tmp_path / "plan_contacts.csv").open()))
    assert [r["contact"] for r in rows] == ["1", "2a", "2b", "2c", "3a", "3b", "3c", "4"]
    first = rows[0]
    # contact 1: 1.0 mm tip offset + 0.75 mm above the target, inside the 6 mm sphere
    assert np.allclose([float(first[k]) for k in "ras"], TARGET + [0, 0, 1.75], atol=1e-3)
    assert np.allclose([float(first[k]) for k in ("lat", "ap", "vert")],
                       frame.to_acpc(TARGET + [0, 0, 1.75]), atol=1e-3)
    assert first["structure"] == "target sphere"
    assert float(first["distance_mm"]) == pytest.approx(1.75 - 6.0, abs=0.03)


def test_lead_depth_must_be_a_number():
    with pytest.raises(PlanningError, match="lead depth must be a finite number"):
        place_lead(Trajectory(ENTRY, TARGET), "medtronic-3389", depth_mm=float("nan"))


def test_contact_bands_for_drawing_span_each_contact():
    placed = place_lead(Trajectory(ENTRY, TARGET), "boston-cartesia-directional")
    bands = contact_extents(placed)
    assert len(bands) == 8
    # contact 1: 1.0 to 2.5 mm above the tip; level 2 segments 3.0 to 4.5 mm
    assert np.allclose(bands[0]["start"], TARGET + [0, 0, 1.0])
    assert np.allclose(bands[0]["end"], TARGET + [0, 0, 2.5])
    assert np.allclose(bands[1]["start"], TARGET + [0, 0, 3.0]) and bands[1]["arc_deg"] == 90.0
    assert "angle_deg" not in bands[0] and bands[0]["radius_mm"] == pytest.approx(0.65)
