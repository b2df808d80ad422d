"""The planning tools driven like a user: landmarks, target, entry, read-outs, session, export."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from app.model.state import FRAME_NAMES, Points  # noqa: E402
from core.evaluation.simulated_user import simulate_user  # noqa: E402
from core.planning.frames import ACPCFrame, volume_centroid  # noqa: E402

# AC, PC and a midline point of the MNI template, roughly where they are (mm)
AC, PC, MID = np.array([0.0, 2.0, -4.0]), np.array([0.0, -24.0, -2.0]), np.array([0.0, -10.0, 40.0])


def _set_at(window, name, xyz):
    window.state.set_crosshair(xyz)
    window.plan.panel.set_landmark(name)


def test_landmarks_give_acpc_readouts_and_are_undoable(window):
    panel, planning = window.plan.panel, window.plan.planning
    _set_at(window, "ac", AC)
    assert planning.frame() is None and "PC" in panel.frame_label.text()
    _set_at(window, "pc", AC)                      # AC = PC: refused, clearly
    _set_at(window, "midline", MID)
    assert planning.frame() is None
    assert "apart" in panel.frame_label.text()
    assert window.plan.planning.undo() and window.plan.planning.undo()   # back to AC only
    assert planning.landmarks["pc"] is None
    _set_at(window, "pc", PC)
    _set_at(window, "midline", MID)
    frame = planning.frame()
    assert frame is not None and frame.ac_pc_distance == pytest.approx(np.linalg.norm(AC - PC))
    # the status bar gives AC-PC coordinates of the crosshair: the MCP is the origin
    window.state.set_crosshair((AC + PC) / 2)
    text = window.cursor_label.text()
    assert "AC-PC:" in text and "lat +0.0" in text and "AP +0.0" in text


def test_trajectory_readouts_crossings_and_probe_view(window):
    planning, panel, state = window.plan.planning, window.plan.panel, window.state
    for name, xyz in (("ac", AC), ("pc", PC), ("midline", MID)):
        _set_at(window, name, xyz)
    target = planning.target_of(state.active)      # the model's default: its centroid
    np.testing.assert_allclose(target, volume_centroid(state.active.surface_vertices(),
                                                       state.active.model.faces), atol=1e-6)
    entry = target + np.array([-20.0, 25.0, 55.0])
    state.set_crosshair(entry)
    panel.set_entry_here()
    traj = planning.trajectory_of(state.active)
    assert traj is not None
    text = panel.trajectory_label.text()
    assert f"Length {np.linalg.norm(traj.target - traj.entry):.1f} mm" in text
    assert "Ring" in text and "arc" in text
    # the trajectory ends at the centroid, inside the caudate: it enters it once
    assert text.count("→") >= 1
    angles = traj.angles(ACPCFrame.from_points(AC, PC, MID))
    assert f"Ring {angles['ring_deg']:.1f}°" in text
    assert panel.probe._image is not None           # the probe's-eye slice is shown
    panel.set_depth_mm(5.0)
    assert panel.probe.depth == pytest.approx(5.0)
    # a user target replaces the model's, and "Model target" brings it back
    state.set_crosshair(target + [1.0, 0.0, 0.0])
    panel.set_target_here()
    assert not planning.target_is_default(state.active)
    np.testing.assert_allclose(planning.target_of(state.active), target + [1, 0, 0], atol=1.01)


def test_plan_survives_save_and_reopen_and_exports(window, tmp_path, qtbot):
    planning, panel, state = window.plan.planning, window.plan.panel, window.state
    for name, xyz in (("ac", AC), ("pc", PC), ("midline", MID)):
        _set_at(window, name, xyz)
    target = planning.target_of(state.active)
    state.set_crosshair(target + [0, 0, 60.0])
    panel.set_entry_here()
    session = tmp_path / "s.json"
    assert window.save_session(path=session)
    doc = json.loads(session.read_text())
    assert doc["info"]["planning"]["ac"] == pytest.approx(AC.tolist())
    window.plan.planning.apply_document(None)
    assert planning.frame() is None
    window.open_session(session)
    assert planning.frame() is not None
    assert planning.trajectory_of(state.active) is not None
    written = window.plan.export(tmp_path / "out")
    names = {p.name for p in written}
    assert {"plan.json", "plan_structures.csv", "plan.mrk.json", "plan_labels.seg.nrrd",
            "plan_labels.nii.gz", "plan_labels.txt"} <= names
    report = json.loads((tmp_path / "out" / "plan.json").read_text())
    row = report["structures"][0]
    # the crosshair snaps to voxel centres: the entry is within half a voxel of where it was put
    expected = np.linalg.norm(planning.entry_of(state.active) - planning.target_of(state.active))
    assert row["trajectory"]["length_mm"] == pytest.approx(expected, abs=1e-6)
    assert abs(expected - 60.0) < 1.0
    assert row["volume_mm3"] > 1000       # a caudate is a few cm^3


def test_uncertainty_and_next_slice(window):
    panel, state = window.plan.panel, window.state
    panel.uncertainty_check.setChecked(True)
    assert "Surface SD" in panel.uncertainty_label.text()
    assert "is uncertain" in panel.uncertainty_label.text()   # the pose or the shape: what, not only how much
    sd_prior = window.plan.last_sd.mean()
    before = state.crosshair.copy()
    window.plan.suggest_next_slice()
    assert not np.allclose(before, state.crosshair)
    # three contours make the surface more certain than the prior alone
    user = simulate_user(state.active.surface_vertices(), state.active.model.faces, 3,
                         rng=np.random.default_rng(0), noise=0.1)
    axis = np.argmax(np.abs([n for _, n in user.planes]), axis=1)[user.contour]
    frames = np.array([FRAME_NAMES.index(("sagittal", "coronal", "axial")[a]) for a in axis])
    depths = user.points[np.arange(len(axis)), axis]
    state.active.set_points(Points(user.points, frames, depths))
    assert window.plan.posterior().vertex_sd().mean() < sd_prior


def test_plan_cli_gives_the_gui_report_from_the_saved_session(window, tmp_path, capsys):
    """``ssm-studio plan`` recomputes, headless, the report the GUI exports."""
    from core.cli import main as cli_main

    planning, panel, state = window.plan.planning, window.plan.panel, window.state
    for name, xyz in (("ac", AC), ("pc", PC), ("midline", MID)):
        _set_at(window, name, xyz)
    state.set_crosshair(planning.target_of(state.active) + [5.0, 20.0, 55.0])
    panel.set_entry_here()
    session = tmp_path / "s.json"
    assert window.save_session(path=session)
    gui = planning.report()
    assert cli_main(["plan", "--session", str(session), "--out", str(tmp_path / "plan.json"),
                     "--export", str(tmp_path / "files")]) == 0
    assert "1 trajectory" in capsys.readouterr().out
    cli = json.loads((tmp_path / "plan.json").read_text())
    a, b = gui["structures"][0], cli["structures"][0]
    assert b["volume_mm3"] == pytest.approx(a["volume_mm3"], rel=1e-9)
    np.testing.assert_allclose(b["trajectory"]["target"], a["trajectory"]["target"], atol=1e-9)
    assert b["trajectory"]["ring_deg"] == pytest.approx(a["trajectory"]["ring_deg"], abs=1e-9)
    assert [c["enter_mm"] for c in b["trajectory"]["crossings"]] == pytest.approx(
        [c["enter_mm"] for c in a["trajectory"]["crossings"]], abs=1e-9)
    assert (tmp_path / "files" / "plan_labels.seg.nrrd").exists()
    # a session without a plan still gives the structure table, without AC-PC
    planning.apply_document(None)
    assert window.save_session(path=session)
    assert cli_main(["plan", "--session", str(session), "--out", str(tmp_path / "p2.json")]) == 0
    assert "acpc" not in json.loads((tmp_path / "p2.json").read_text())


def test_two_structures_plan_in_gui_and_headless(window, tmp_path, resources_dir):
    """Two library structures, a trajectory each: the saved session plans both headless."""
    from app.model.state import Structure
    from core.cli import main as cli_main

    planning, panel, state = window.plan.planning, window.plan.panel, window.state
    right = state.add_structure(Structure())
    window.sessions.open_model(resources_dir / "models" / "right_caudate.npz", structure=right)
    assert state.active is right and right.side == "right"
    for s, offset in ((state.structures[0], [-10.0, 20.0, 55.0]), (right, [10.0, 20.0, 55.0])):
        state.set_active(s)
        state.set_crosshair(planning.target_of(s) + offset)
        panel.set_entry_here()
    for name, xyz in (("ac", AC), ("pc", PC), ("midline", MID)):
        _set_at(window, name, xyz)
    session = tmp_path / "two.json"
    assert window.save_session(path=session)
    assert cli_main(["plan", "--session", str(session), "--out", str(tmp_path / "plan.json")]) == 0
    rows = json.loads((tmp_path / "plan.json").read_text())["structures"]
    assert len(rows) == 2 and all("trajectory" in r for r in rows)
    assert rows[0]["centroid_acpc"][0] < 0 < rows[1]["centroid_acpc"][0]   # left, right
    assert "right" in rows[1]["name"]
    gui = planning.report()["structures"]
    for a, b in zip(gui, rows):
        np.testing.assert_allclose(a["trajectory"]["entry"], b["trajectory"]["entry"], atol=1e-9)
        assert a["volume_mm3"] == pytest.approx(b["volume_mm3"], rel=1e-9)
