"""Planning geometry against known answers: AC-PC frames, trajectory angles, crossings, volumes."""

from __future__ import annotations

import numpy as np
import pytest
from analytic import sphere as icosphere
from scipy.spatial.transform import Rotation

from core.geometry.mesh import volume
from core.planning.frames import (
    ACPCFrame,
    PlanningError,
    Trajectory,
    anchored_point,
    anchored_point_weights,
    format_acpc,
    ray_surface_crossings,
    structure_row,
    volume_centroid,
)


def _synthetic_frame(seed: int = 0):
    rng = np.random.default_rng(seed)
    rot = Rotation.from_rotvec(rng.normal(scale=0.3, size=3)).as_matrix()  # rows: lat, ant, up
    origin = rng.uniform(-50, 50, size=3) + np.array([0, 0, 1000.0])  # scanner-like offset
    ac = origin + 12.5 * rot[1]
    pc = origin - 12.5 * rot[1]
    midline = origin + 30.0 * rot[2] + 7.0 * rot[1]  # anywhere in the midsagittal plane
    return rot, origin, ac, pc, midline


def test_acpc_coordinates_of_known_points():
    rot, origin, ac, pc, midline = _synthetic_frame()
    frame = ACPCFrame.from_points(ac, pc, midline)
    q = np.random.default_rng(1).uniform(-40, 40, size=(50, 3))
    world = q @ rot + origin
    np.testing.assert_allclose(frame.to_acpc(world), q, atol=1e-9)
    np.testing.assert_allclose(frame.to_world(q), world, atol=1e-9)
    np.testing.assert_allclose(frame.to_acpc(ac), [0, 12.5, 0], atol=1e-9)
    assert frame.ac_pc_distance == pytest.approx(25.0)
    m = frame.matrix()
    np.testing.assert_allclose((world @ m[:3, :3].T) + m[:3, 3], q, atol=1e-9)


def test_acpc_lateral_axis_points_right():
    # AC anterior of PC, midline above, in plain RAS: lateral must be +x (right)
    frame = ACPCFrame.from_points([0, 12, 0], [0, -12, 0], [0, 0, 40])
    np.testing.assert_allclose(frame.to_acpc([10, 0, 0]), [10, 0, 0], atol=1e-12)
    assert "(R)" in format_acpc(frame.to_acpc([10, 0, 0]))
    assert "(L)" in format_acpc(frame.to_acpc([-10, 0, 0]))


@pytest.mark.parametrize("ac, pc, midline, message", [
    ([0, 0, 0], [0, 0, 0], [0, 0, 40], "apart"),
    ([0, 1, 0], [0, -1, 0], [0, 0, 40], "apart"),
    ([0, 12, 0], [0, -12, 0], [0, 30, 0.5], "AC-PC line"),
    ([0, 12, 0], [0, -12, 0], [0, 0, np.nan], "finite"),
])
def test_acpc_degenerate_input_refused(ac, pc, midline, message):
    with pytest.raises(PlanningError, match=message):
        ACPCFrame.from_points(ac, pc, midline)


def test_trajectory_angles():
    frame = ACPCFrame.from_points([0, 12, 0], [0, -12, 0], [0, 0, 40])
    target = np.array([12.0, -3.0, -4.0])
    vertical = Trajectory(target + [0, 0, 60], target)
    assert vertical.length == pytest.approx(60)
    a = vertical.angles(frame)
    assert a["ring_deg"] == pytest.approx(90) and a["arc_deg"] == pytest.approx(90)
    assert a["midsagittal_angle_deg"] == pytest.approx(0, abs=1e-9)
    # entry 30 degrees anterior of vertical (sagittal) -> ring 60
    up = np.array([0, np.sin(np.radians(30)), np.cos(np.radians(30))])
    a = Trajectory(target + 70 * up, target).angles(frame)
    assert a["ring_deg"] == pytest.approx(60) and a["arc_deg"] == pytest.approx(90)
    # entry 20 degrees to the right (coronal) -> arc 70, 20 degrees off the midsagittal plane
    up = np.array([np.sin(np.radians(20)), 0, np.cos(np.radians(20))])
    a = Trajectory(target + 70 * up, target).angles(frame)
    assert a["arc_deg"] == pytest.approx(70) and a["ring_deg"] == pytest.approx(90)
    assert a["midsagittal_angle_deg"] == pytest.approx(20)


def test_trajectory_angles_follow_a_rotated_frame():
    rot, origin, ac, pc, midline = _synthetic_frame(3)
    frame = ACPCFrame.from_points(ac, pc, midline)
    up_acpc = np.array([np.sin(np.radians(20)), 0, np.cos(np.radians(20))])
    target = origin + 10 * rot[0]
    a = Trajectory(target + 50 * (up_acpc @ rot), target).angles(frame)
    assert a["arc_deg"] == pytest.approx(70) and a["ring_deg"] == pytest.approx(90)


def test_trajectory_crosses_sphere_where_expected():
    r, c = 10.0, np.array([5.0, -20.0, 30.0])
    v, f = icosphere(r, c, 5)
    sagitta = r * 0.002  # icosphere(5) facets stay within 0.2 % of the radius
    entry = c + [0, 0, 80.0]
    target = c - [0, 0, 5.0]
    traj = Trajectory(entry, target)
    hits = traj.crossings(v, f)
    assert len(hits) == 1 and hits[0].entering
    assert hits[0].distance == pytest.approx(70.0, abs=sagitta)
    inside = traj.segments_inside(v, f, extend=20.0)
    assert len(inside) == 1
    assert inside[0][0] == pytest.approx(70.0, abs=sagitta)
    assert inside[0][1] == pytest.approx(90.0, abs=sagitta)
    # an off-centre chord: half-length sqrt(r^2 - h^2)
    h = 6.0
    traj = Trajectory(c + [h, 0, 50.0], c + [h, 0, -50.0])
    (enter, leave), = traj.segments_inside(v, f)
    half = np.sqrt(r * r - h * h)
    assert enter == pytest.approx(50 - half, abs=0.05) and leave == pytest.approx(50 + half, abs=0.05)
    # a miss
    assert Trajectory(c + [r + 1, 0, 50], c + [r + 1, 0, -50]).crossings(v, f) == []


def test_ray_inside_two_pieces_gives_two_intervals():
    v1, f1 = icosphere(5.0, [0, 0, 0], 3)
    v2, f2 = icosphere(5.0, [0, 0, 20], 3)
    v = np.vstack([v1, v2])
    f = np.vstack([f1, f2 + len(v1)])
    inside = Trajectory([0, 0, 50], [0, 0, -50]).segments_inside(v, f)
    assert len(inside) == 2
    np.testing.assert_allclose([inside[0][1] - inside[0][0], inside[1][1] - inside[1][0]],
                               [10, 10], atol=0.1)
    hits = ray_surface_crossings([0, 0, 50], [0, 0, -1], v, f)
    assert [h.entering for h in hits] == [True, False, True, False]


def test_volume_and_centroid_of_analytic_shapes():
    r, c = 7.0, np.array([-14.0, 12.0, 1010.0])
    v, f = icosphere(r, c, 5)
    analytic = 4 / 3 * np.pi * r ** 3
    assert abs(volume(v, f)) == pytest.approx(analytic, rel=0.01)
    np.testing.assert_allclose(volume_centroid(v, f), c, atol=1e-6)
    # a box: 8 vertices, 12 outward triangles, centroid at its centre
    lo, hi = np.array([1.0, 2.0, 3.0]), np.array([4.0, 7.0, 5.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                      [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    np.testing.assert_allclose(volume_centroid(corners, faces), (lo + hi) / 2, atol=1e-12)
    row = structure_row("box", corners, faces, ACPCFrame.from_points([0, 12, 0], [0, -12, 0],
                                                                     [0, 0, 40]))
    assert row["volume_mm3"] == pytest.approx(np.prod(hi - lo))
    np.testing.assert_allclose(row["centroid_acpc"], (lo + hi) / 2, atol=1e-12)


def test_anchored_point_moves_with_an_affine_deformation():
    v, _ = icosphere(10.0, [0, 0, 0], 3)
    point = np.array([2.0, -3.0, 1.5])
    idx, w = anchored_point_weights(v, point)
    np.testing.assert_allclose(anchored_point(v, idx, w), point, atol=1e-3)
    a = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.2]])
    t = np.array([5.0, -7.0, 3.0])
    np.testing.assert_allclose(anchored_point(v @ a.T + t, idx, w), a @ point + t, atol=1e-3)
