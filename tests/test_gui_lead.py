"""Issue 29 in the GUI: a lead on the trajectory (type, depth, rotation; contacts drawn in the
slice views and in 3D; the contact read-out), the trajectory's warnings, and *Export all*
writing every structure."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytestmark = pytest.mark.gui

from core.io.model_library import RESOURCES_MODELS  # noqa: E402
from core.planning.frames import ACPCFrame  # noqa: E402
from core.planning.report import LeadChoice  # noqa: E402

AC, PC, MID = np.array([0.0, 2.0, -4.0]), np.array([0.0, -24.0, -2.0]), np.array([0.0, -10.0, 40.0])


def _plan(window, entry_offset=(0.0, 0.0, 60.0)):
    """AC, PC, midline and an entry above the demo structure's model target."""
    planning, state = window.plan.planning, window.state
    for name, xyz in (("ac", AC), ("pc", PC), ("midline", MID)):
        planning.set_landmark(name, xyz)
    target = planning.target_of(state.active)
    planning.set_entry(state.active, target + np.asarray(entry_offset))
    return target


def _choose(panel, key, depth=0.0, rotation=0.0):
    panel.lead_depth.setValue(depth)
    panel.lead_rotation.setValue(rotation)
    panel.lead_combo.setCurrentIndex(panel.lead_combo.findData(key))


def test_readout_lists_the_four_contacts_of_a_3389_with_their_structure(window):
    planning, panel, state = window.plan.planning, window.plan.panel, window.state
    target = _plan(window)
    _choose(panel, "medtronic-3389")
    assert planning.lead_of(state.active) == LeadChoice("medtronic-3389", 0.0, 0.0)
    table = panel.contact_table
    assert table.rowCount() == 4
    assert [table.item(i, 0).text() for i in range(4)] == ["0", "1", "2", "3"]
    # the tip at the (model's default) target, straight below the entry: contact k's centre
    # 1.5 + 0.75 + 2 k mm above it (Medtronic 3389: 1.5 mm contacts 0.5 mm apart)
    frame = ACPCFrame.from_points(AC, PC, MID)
    for k in range(4):
        centre = target + [0.0, 0.0, 2.25 + 2.0 * k]
        expected = "{:+.1f}, {:+.1f}, {:+.1f}".format(*frame.to_acpc(centre))
        assert table.item(k, 1).text() == expected
    # the model's target is the structure's centroid: the lowest contact lies in it
    assert table.item(0, 2).text() == state.active.label
    assert float(table.item(0, 3).text()) < 0
    # the lead is one undoable plan edit
    assert planning.undo()
    assert planning.lead_of(state.active) is None and table.rowCount() == 0
    assert planning.redo() and table.rowCount() == 4
    # a deeper tip moves every contact by as much; a directional lead has 8 contacts
    panel.lead_depth.setValue(3.0)
    panel.lead_depth.editingFinished.emit()
    tip = planning.placed_lead_of(state.active).tip
    np.testing.assert_allclose(tip, target - [0.0, 0.0, 3.0], atol=1e-9)
    _choose(panel, "boston-cartesia-directional", 0.0, 30.0)
    assert table.rowCount() == 8 and panel.lead_rotation.isEnabled()
    assert table.item(1, 0).text() == "2a"


def test_contact_bands_sit_at_the_contacts_world_positions_in_a_slice(window):
    planning, state = window.plan.planning, window.state
    volume = state.volume
    # a target on a voxel centre and a vertical trajectory; tip 0.25 mm past the target puts
    # contact 1's centre (0.25 below + 1.5 + 0.75 + 2 mm above) on the slice 4 mm above
    target = volume.voxel_to_world(np.round(volume.world_to_voxel(planning.target_of(state.active))))
    planning.set_target(state.active, target)
    planning.set_entry(state.active, target + [0.0, 0.0, 60.0])
    planning.set_lead(state.active, LeadChoice("medtronic-3389", 0.25))
    state.set_crosshair(target + [0.0, 0.0, 4.0])
    view = window.workspace.views["coronal"]
    bands = window.plan.slice_overlay.contact_bands(view, planning.placed_lead_of(state.active))
    assert [b[0] for b in bands] == ["0", "1", "2", "3"]
    for k, (_, a, b, width, crosses) in enumerate(bands):
        low = target + [0.0, 0.0, -0.25 + 1.5 + 2.0 * k]
        np.testing.assert_allclose(a, view.world_to_screen(low), atol=1e-6)
        np.testing.assert_allclose(b, view.world_to_screen(low + [0.0, 0.0, 1.5]), atol=1e-6)
        assert crosses                         # the coronal slice holds the whole lead
        # as wide on screen as the lead's 1.27 mm
        assert width == pytest.approx(max(3.0, 1.27 * abs(view.world_to_screen(low + [1, 0, 0])[0]
                                                           - a[0])), rel=1e-6)
    axial = window.workspace.views["axial"]
    crossing = [b[0] for b in window.plan.slice_overlay.contact_bands(
        axial, planning.placed_lead_of(state.active)) if b[4]]
    assert crossing == ["1"]
    window.workspace.views["axial"].grab()     # paints without error


def test_warnings_in_red_when_the_target_lies_outside_its_structure(window):
    planning, panel, state = window.plan.planning, window.plan.panel, window.state
    _plan(window)
    assert "outside" not in panel.warnings_label.text()
    outside = state.active.surface_vertices()[:, 0].max() + 6.0
    target = planning.target_of(state.active).copy()
    target[0] = outside
    planning.set_target(state.active, target)
    text = panel.warnings_label.text()
    assert "outside" in text and state.active.label in text
    assert "e03030" in panel.warnings_label.styleSheet()
    shown = float(text.split("lies ")[1].split(" mm")[0])
    # every surface point has x <= the extreme: at least 6 mm; at most the nearest vertex
    nearest_vertex = float(np.linalg.norm(state.active.surface_vertices() - target, axis=1).min())
    assert 6.0 - 0.05 <= shown <= nearest_vertex + 0.05


def test_the_ventricles_are_warned_about_where_the_library_models_put_them(window):
    """The GUI checks the path against the demo template's ventricles placed as the library
    models are (as ``ssm-studio plan`` does): the same crossing depths as core's check of the
    ventricles mapped by that placement; none once the template is placed elsewhere."""
    from core.planning.frames import template_ventricles, trajectory_warnings
    from core.planning.report import template_to_image

    planning, panel, state = window.plan.planning, window.plan.panel, window.state
    _plan(window)
    placement = template_to_image(state)
    assert placement is not None                                   # the demo's library model
    expected = trajectory_warnings(planning.trajectory_of(state.active), None,
                                   [template_ventricles(placement)])
    shown = [w for w in planning.warnings_of(state.active) if w["kind"] == "crosses_ventricle"]
    assert expected and [w["kind"] for w in expected] == ["crosses_ventricle"]
    assert np.allclose(shown[0]["intervals_mm"], expected[0]["intervals_mm"], atol=1e-9)
    assert "crosses the ventricles" in panel.warnings_label.text()
    # the library model placed 40 mm to the side (as a placement would): the ventricles go
    # with it, off this path
    moved = state.active.placement.copy()
    moved[0, 3] += 40.0
    state.active.placement = moved
    assert not [w for w in planning.warnings_of(state.active) if w["kind"] == "crosses_ventricle"]


def test_a_session_with_a_lead_round_trips(window, tmp_path):
    planning, state = window.plan.planning, window.state
    _plan(window)
    planning.set_lead(state.active, LeadChoice("boston-cartesia-directional", -1.5, 60.0))
    session = tmp_path / "lead.json"
    assert window.save_session(path=session)
    doc = json.loads(session.read_text())
    assert doc["info"]["planning"]["structures"][0]["lead"] == {
        "type": "boston-cartesia-directional", "depth_mm": -1.5, "rotation_deg": 60.0}
    before = planning.placed_lead_of(state.active)
    planning.apply_document(None)
    assert planning.lead_of(state.active) is None
    window.open_session(session)
    after = planning.placed_lead_of(window.state.active)
    assert after is not None and after.lead.key == "boston-cartesia-directional"
    np.testing.assert_allclose([c.centre for c in after.contacts],
                               [c.centre for c in before.contacts], atol=1e-9)
    # Export plan... reads the contacts out in the report and contacts CSV
    written = {p.name for p in window.plan.export(tmp_path / "plan")}
    assert "plan_contacts.csv" in written
    report = json.loads((tmp_path / "plan" / "plan.json").read_text())
    contacts = report["structures"][0]["trajectory"]["lead"]["contacts"]
    assert len(contacts) == 8 and contacts[1]["contact"] == "2a"
    # an older session's planning block (no "lead" key) still opens
    del doc["info"]["planning"]["structures"][0]["lead"]
    session.write_text(json.dumps(doc))
    window.open_session(session)
    assert window.plan.planning.lead_of(window.state.active) is None
    assert window.plan.planning.trajectory_of(window.state.active) is not None


def test_export_all_writes_every_structure_as_dicom_seg_and_rtstruct(make_window, tmp_path):
    import pydicom
    from test_dbs_workflow import write_series

    from app import demo
    from core.io import load_volume
    if demo.demo_image() is None:
        pytest.skip("no demo image")
    t1 = load_volume(demo.demo_image())
    # the demo T1 around the basal ganglia as an axial DICOM series (1 mm, LPS origin)
    # (DICOM rows run to the patient's left and columns to posterior: the RAS template's
    # first two axes reversed, from its far corner)
    crop = t1.data[50:150, 90:190, 60:110][::-1, ::-1]
    origin_ras = t1.voxel_to_world(np.array([149.0, 189.0, 60.0]))
    series = write_series(tmp_path / "series", np.clip(crop, 0, None) * 10,
                          (1.0, 1.0, 1.0), origin_ras * [-1, -1, 1])
    window = make_window(load_demo=False)
    window.load_image(tmp_path / "series")
    assert window.add_structure(RESOURCES_MODELS / "left_caudate.npz")
    assert window.add_structure(RESOURCES_MODELS / "left_thalamus.npz")
    n = sum(s.model is not None for s in window.state.structures)
    assert n == 2
    written = window.export_all(tmp_path / "out")
    names = {p.name for p in written}
    assert {"all_labels.seg.nrrd", "all_structures.seg.dcm",
            "all_structures.rtstruct.dcm"} <= names
    seg = pydicom.dcmread(tmp_path / "out" / "all_structures.seg.dcm")
    labels = [s.label for s in window.state.structures if s.model is not None]
    assert [item.SegmentLabel for item in seg.SegmentSequence] == labels
    rt = pydicom.dcmread(tmp_path / "out" / "all_structures.rtstruct.dcm")
    assert [r.ROIName for r in rt.StructureSetROISequence] == labels
    assert len(series) == 50
    # the engine reports each file it writes (the GUI's progress dialog), and a cancel through
    # that callback stops before the next file
    from core.planning.report import export_all_structures
    from core.runtime.progress import Cancelled

    seen = []

    def stop_at_dicom(fraction, message=""):
        seen.append(message)
        if "DICOM" in message:
            raise Cancelled()

    with pytest.raises(Cancelled):
        export_all_structures(tmp_path / "cancelled", window.plan.planning.planned_structures(),
                              window.state.volume, stem="all", dicom_series=series,
                              meshes=False, progress=stop_at_dicom)
    assert len(seen) == 3
    assert (tmp_path / "cancelled" / "all_labels.seg.nrrd").exists()
    assert not (tmp_path / "cancelled" / "all_structures.seg.dcm").exists()
