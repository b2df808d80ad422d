"""Tests for core.session: session files (relative paths, versions, bad files: document.py) and
crash recovery (recovery.py)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from recovery_runs import crashing_run

from core.io import DataFileError
from core.session import document as sessions
from core.session import recovery as rec
from core.session.document import Session

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def state_dir(tmp_path, monkeypatch) -> Path:
    """Every test gets its own recovery folder."""
    folder = tmp_path / "state"
    monkeypatch.setenv("SSM_STUDIO_STATE_DIR", str(folder))
    return folder


@pytest.fixture
def recovery(state_dir) -> rec.CrashRecovery:
    """This process's autosave in the test's recovery folder; cleared (lock released) after."""
    autosave = rec.CrashRecovery()
    yield autosave
    autosave.clear()


def full_session(folder: Path, n_points: int = 40) -> Session:
    rng = np.random.default_rng(3)
    points = rng.normal(scale=20.0, size=(n_points, 3)) + [10.0, -15.0, 4.0]
    normals = rng.normal(size=(n_points, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    planes = [("axial", "coronal", "sagittal")[i % 3] for i in range(n_points)]
    depths = [points[i, {"sagittal": 0, "coronal": 1, "axial": 2}[p]] for i, p in enumerate(planes)]
    pose = np.eye(4)
    pose[:3, :3] = 1.1 * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    pose[:3, 3] = [1.5, -2.25, 3.125]
    return Session(image_path=folder / "scans" / "t1.nii.gz", model_path=folder / "stn.npz",
                   points=points, normals=normals, point_slices=list(zip(planes, depths)),
                   coef=rng.normal(size=7), pose=pose, fit_method="gmm-aniso",
                   prior_weight=0.25, fit={"pose": "similarity"}, window=(812.5, 301.0),
                   crosshair=[1.0, 2.0, 3.0], info={"note": "left STN"})


def assert_same(a: Session, b: Session) -> None:
    for name in ("points", "normals", "coef", "pose", "crosshair"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.point_slices == b.point_slices
    assert a.window == b.window
    assert a.fit == b.fit


# --------------------------------------------------------------------------------------
# Session files
# --------------------------------------------------------------------------------------


def test_round_trip_relative_paths_survive_moving_the_folder(tmp_path):
    project = tmp_path / "case01"
    (project / "scans").mkdir(parents=True)
    (project / "scans" / "t1.nii.gz").write_bytes(b"image")
    (project / "stn.npz").write_bytes(b"model")
    session = full_session(project)
    sessions.save_session(project / "sessions" / "left.json", session)

    doc = json.loads((project / "sessions" / "left.json").read_text())
    assert doc["format"] == "ssm-studio-session"
    assert doc["format_version"] == 1
    assert doc["image"] == "../scans/t1.nii.gz"
    assert doc["model"] == "../stn.npz"
    assert doc["fit"] == {"pose": "similarity", "method": "gmm-aniso", "prior_weight": 0.25}
    assert doc["point_slices"][0] == ["axial", session.point_slices[0][1]]

    moved = tmp_path / "archive" / "case01-copy"
    moved.parent.mkdir()
    shutil.move(str(project), str(moved))
    back = sessions.load_session(moved / "sessions" / "left.json")
    assert back.image_path == moved / "scans" / "t1.nii.gz"
    assert back.model_path == moved / "stn.npz"
    assert back.image_path.read_bytes() == b"image"
    assert back.missing_files() == []
    assert_same(back, session)  # floats are written exactly (shortest repr)
    assert back.fit_method == "gmm-aniso"
    assert back.prior_weight == 0.25
    assert back.info["note"] == "left STN"


def test_session_file_moved_alone_finds_data_by_absolute_path(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "scan.nii").write_bytes(b"image")
    sessions.save_session(tmp_path / "work" / "s.json", Session(image=tmp_path / "data" / "scan.nii"))
    assert json.loads((tmp_path / "work" / "s.json").read_text())["image"] == "../data/scan.nii"
    (tmp_path / "elsewhere" / "deeper").mkdir(parents=True)
    os.replace(tmp_path / "work" / "s.json", tmp_path / "elsewhere" / "deeper" / "s.json")
    back = sessions.load_session(tmp_path / "elsewhere" / "deeper" / "s.json")
    assert back.image_path == tmp_path / "data" / "scan.nii"
    assert back.missing_files() == []


def test_paths_outside_the_folder_and_missing_files(tmp_path):
    session = Session(image="/somewhere/else/scan.nii", points=np.zeros((0, 3)))
    sessions.save_session(tmp_path / "s.json", session)
    doc = json.loads((tmp_path / "s.json").read_text())
    assert doc["model"] is None
    back = sessions.load_session(tmp_path / "s.json")
    assert back.image_path == Path("/somewhere/else/scan.nii")
    assert back.model_path is None
    assert back.missing_files() == [Path("/somewhere/else/scan.nii")]
    assert back.n_points == 0 and back.points.shape == (0, 3)
    assert back.point_slices is None and back.coef is None and back.pose is None


def test_gui_style_constructor_and_axis_numbers():
    session = Session(image="scan.nii", model="m.npz", points=[[1, 2, 3], [4, 5, 6]],
                      point_slices=[["axial", 3.0], [0, 4.0]], window=[100, 50],
                      fit={"method": "icp", "prior_weight": 2})
    assert session.image == "scan.nii" and session.model == "m.npz"
    assert session.point_slices == [("axial", 3.0), ("sagittal", 4.0)]
    np.testing.assert_array_equal(session.point_axes, [2, 0])
    np.testing.assert_array_equal(session.point_depths, [3.0, 4.0])
    assert session.window == (100.0, 50.0)
    assert session.fit_method == "icp" and session.prior_weight == 2.0


@pytest.mark.parametrize("kwargs, phrase", [
    ({"points": np.zeros((3, 2))}, "points must be (P, 3)"),
    ({"points": np.zeros((3, 3)), "normals": np.zeros((2, 3))}, "normals must be (3, 3)"),
    ({"points": np.zeros((2, 3)), "point_slices": [("axial", 1.0)]}, "one entry per point (2)"),
    ({"points": np.zeros((1, 3)), "point_slices": [("oblique", 1.0)]}, "unknown plane 'oblique'"),
    ({"pose": np.eye(3)}, "pose must be 4x4"),
    ({"pose": np.zeros((4, 4))}, "invertible"),
    ({"points": [[0.0, np.nan, 1.0]]}, "points contain NaN"),
    ({"coef": ["a", "b"]}, "coef must be numbers"),
    ({"crosshair": [1.0, 2.0]}, "crosshair must be (3,)"),
    ({"window": [1.0, 2.0, 3.0]}, "window must be [width, level]"),
])
def test_invalid_sessions_are_refused(kwargs, phrase):
    with pytest.raises(ValueError) as info:
        Session(**kwargs)
    assert phrase in str(info.value)


def _valid_doc() -> dict:
    return {"format": "ssm-studio-session", "format_version": 1, "image": "a.nii",
            "model": None, "points": [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], "normals": None,
            "point_slices": [["axial", 3.0], ["axial", 6.0]], "coef": [0.5, -1.0],
            "pose": np.eye(4).tolist(), "fit": {"method": "gmm-iso"}, "window": [10, 5],
            "crosshair": [0, 0, 0], "info": {}}


def _doc_with(**changes) -> dict:
    doc = _valid_doc()
    doc.update(changes)
    return doc


BAD_SESSION_FILES = [
    ("missing.json", None, "file not found"),
    ("empty.json", b"", "file is empty"),
    ("cut.json", json.dumps(_valid_doc())[:70].encode(), "not valid JSON"),
    ("binary.json", b"\x89PNG\r\n\x1a\n\x00\x00\xff", "not UTF-8 text"),
    ("list.json", b"[1, 2, 3]", "the JSON is not an object"),
    ("other.json", json.dumps({"format": "slicer-scene"}).encode(), "not an SSM Studio session"),
    ("future.json", json.dumps(_doc_with(format_version=7)).encode(),
     "session format version 7 is newer than this SSM Studio reads (version 1)"),
    ("noversion.json", json.dumps(_doc_with(format_version=None)).encode(),
     "no valid format_version"),
    ("points.json", json.dumps(_doc_with(points=[[1, 2], [3, 4]])).encode(),
     "points must be (P, 3)"),
    ("slices.json", json.dumps(_doc_with(point_slices=[["axial", 1.0]])).encode(),
     "point_slices must have one entry per point"),
    ("plane.json", json.dumps(_doc_with(point_slices=[["diagonal", 1], ["axial", 2]])).encode(),
     "unknown plane 'diagonal'"),
    ("pose.json", json.dumps(_doc_with(pose=[[1, 0], [0, 1]])).encode(), "pose must be 4x4"),
    ("coef.json", json.dumps(_doc_with(coef=["x", 1])).encode(), "coef must be numbers"),
    ("nan.json", b'{"format": "ssm-studio-session", "format_version": 1, '
                 b'"points": [[NaN, 0, 0]]}', "points contain NaN"),
    ("image.json", json.dumps(_doc_with(image=42)).encode(), "'image' must be a file path"),
    ("fit.json", json.dumps(_doc_with(fit=[1, 2])).encode(), "'fit' must be a JSON object"),
    ("packed.json", json.dumps(_doc_with(points={"dtype": "<f8", "shape": [2, 3],
                                                  "base64": "!!"})).encode(),
     "points is not a valid packed array"),
]


@pytest.mark.parametrize("name, content, phrase", BAD_SESSION_FILES,
                         ids=[b[0] for b in BAD_SESSION_FILES])
def test_bad_session_files(tmp_path, name, content, phrase):
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(DataFileError) as info:
        sessions.load_session(path)
    assert str(path) in str(info.value)
    assert phrase in str(info.value), str(info.value)


def test_packed_arrays_are_read_in_session_files(tmp_path):
    points = np.random.default_rng(0).normal(size=(5, 3))
    doc = _doc_with(points=sessions._packed(points), point_slices=None)
    (tmp_path / "p.json").write_text(json.dumps(doc))
    np.testing.assert_array_equal(sessions.load_session(tmp_path / "p.json").points, points)


def test_failed_save_keeps_previous_session(tmp_path, monkeypatch):
    target = tmp_path / "s.json"
    sessions.save_session(target, Session(points=[[1.0, 2.0, 3.0]]))
    before = target.read_bytes()
    bad = Session(points=[[1.0, 2.0, 3.0]])
    bad.points = np.array([[np.nan, 0.0, 0.0]])  # broken after construction
    with pytest.raises(DataFileError, match="cannot save an invalid session"):
        sessions.save_session(target, bad)

    def failing_dumps(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(sessions.json, "dumps", failing_dumps)
    with pytest.raises(OSError):
        sessions.save_session(target, Session(points=[[4.0, 5.0, 6.0]]))
    assert target.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.json"]


# --------------------------------------------------------------------------------------
# Recovery
# --------------------------------------------------------------------------------------


def test_state_dir_defaults(monkeypatch, tmp_path):
    monkeypatch.delenv("SSM_STUDIO_STATE_DIR")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert rec.state_dir() == tmp_path / "xdg" / "ssm-studio"
    monkeypatch.delenv("XDG_STATE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert rec.state_dir() == tmp_path / "home" / ".local" / "state" / "ssm-studio"
    monkeypatch.setenv("XDG_STATE_HOME", "relative/state")  # ignored, as the XDG spec says
    assert rec.state_dir() == tmp_path / "home" / ".local" / "state" / "ssm-studio"


def test_recovery_lifecycle_in_one_run(state_dir, tmp_path, recovery):
    assert recovery.read() is None
    assert not rec.previous_run_crashed()
    session = full_session(tmp_path)
    path = recovery.write(session)
    assert path.parent == state_dir and str(os.getpid()) in path.name
    assert recovery.path == path
    session.points = session.points + 1.0
    second = recovery.write(session)
    assert second != path and recovery.path == second  # the two slots alternate
    # this run's own autosave is never offered as "left by a crash"
    assert recovery.read() is None
    assert not rec.previous_run_crashed()
    recovery.clear()
    assert list(state_dir.iterdir()) == []


def test_crash_leaves_a_recovery_that_is_offered_once(state_dir, tmp_path, recovery):
    pid = crashing_run(state_dir=state_dir, script=f"""
pts = np.arange(1500, dtype=float).reshape(500, 3) / 7
sess = s.Session(image={str(tmp_path / 'scan.nii.gz')!r}, points=pts,
                 point_slices=[("axial", float(z)) for z in pts[:, 2]], coef=[0.1, -0.2],
                 pose=np.eye(4), window=(400.0, 40.0), fit={{"method": "gmm-iso"}})
r.write(sess)
sess.points = pts + 1.0
r.write(sess)""")
    assert pid != os.getpid()
    assert rec.previous_run_crashed()
    assert all(str(pid) in p.name for p in rec.orphaned_recovery_files())

    recovered = recovery.read()
    expected = np.arange(1500, dtype=float).reshape(500, 3) / 7 + 1.0  # the newer autosave
    np.testing.assert_array_equal(recovered.points, expected)
    assert recovered.image_path == tmp_path / "scan.nii.gz"
    assert recovered.point_slices[10] == ("axial", (np.arange(1500).reshape(500, 3)[10, 2]) / 7)
    np.testing.assert_array_equal(recovered.coef, [0.1, -0.2])
    assert recovered.window == (400.0, 40.0) and recovered.fit_method == "gmm-iso"

    # claimed: now this process's file, not offered again, removed by a clean exit
    assert not rec.previous_run_crashed()
    assert recovery.read() is None
    assert all(str(os.getpid()) in p.name for p in state_dir.iterdir())
    recovery.write(recovered)  # this run goes on autosaving
    recovery.clear()
    assert list(state_dir.iterdir()) == []


def test_running_instance_files_are_not_offered(state_dir, tmp_path, recovery):
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        own = recovery.write(Session(points=[[1.0, 2.0, 3.0]]))
        os.replace(own, state_dir / f"recovery-{other.pid}-a.json")
        assert not rec.previous_run_crashed()
        assert recovery.read() is None
    finally:
        other.kill()
        other.wait()
    assert rec.previous_run_crashed()  # that instance has gone without cleaning up
    np.testing.assert_array_equal(recovery.read().points, [[1.0, 2.0, 3.0]])


def test_newest_damaged_slot_falls_back_to_the_older(state_dir, recovery):
    pid = crashing_run(state_dir=state_dir, script="""
r.write(s.Session(points=[[1.0, 1.0, 1.0]]))
newest = r.write(s.Session(points=[[2.0, 2.0, 2.0]]))
newest.write_text(newest.read_text()[:100])   # the crash hit in the middle of a write""")
    recovered = recovery.read()
    np.testing.assert_array_equal(recovered.points, [[1.0, 1.0, 1.0]])
    assert not any(str(pid) in p.name for p in state_dir.iterdir())


def test_damaged_recovery_gives_clear_error_and_is_cleared(state_dir, recovery):
    state_dir.mkdir()
    (state_dir / "recovery-999999999-a.json").write_text('{"format": "ssm-studio-sess')
    assert rec.previous_run_crashed()
    with pytest.raises(DataFileError) as info:
        recovery.read()
    assert "recovery-" in str(info.value) and "not valid JSON" in str(info.value)
    recovery.clear()
    assert list(state_dir.iterdir()) == []
    assert recovery.read() is None


def test_recovery_stores_absolute_paths(tmp_path, monkeypatch, recovery):
    monkeypatch.chdir(tmp_path)
    path = recovery.write(Session(image="scan.nii", model=Path("models") / "m.npz"))
    doc = json.loads(path.read_text())
    assert doc["image"] == str(tmp_path / "scan.nii")
    assert doc["model"] == str(tmp_path / "models" / "m.npz")


# --------------------------------------------------------------------------------------
# Issue 18: deep JSON, options and coefficients that do not fit, PID-only recovery check
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, doc, phrase", [
    ("deep", "[" * 100000 + "]" * 100000, "nested too deeply"),  # was a RecursionError
    ("method", {"fit": {"method": "magic"}}, "fit method 'magic' is not one of"),
    ("pose", {"fit": {"pose": "wobbly"}}, "fit pose 'wobbly' is not one of"),
    ("prior", {"fit": {"prior_weight": -2}}, "prior_weight must be a number >= 0"),
    ("prior_bool", {"fit": {"prior_weight": True}}, "prior_weight must be a number"),
])
def test_session_errors_name_the_session(tmp_path, name, doc, phrase):
    """Before: deep JSON gave a traceback; bad fit options failed later in the GUI's fit
    panel with a message that did not name the session."""
    path = tmp_path / f"{name}.json"
    if isinstance(doc, str):
        path.write_text(doc)
    else:
        path.write_text(json.dumps({"format": "ssm-studio-session", "format_version": 1,
                                    "points": [[1, 2, 3]], **doc}))
    with pytest.raises(DataFileError, match=phrase) as info:
        sessions.load_session(path)
    assert str(info.value).startswith(str(path))


def _model(n_factors: int):
    from core.models.shape_model import ShapeModel

    mean = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    return ShapeModel(mean=mean, factors=np.ones((n_factors, 4, 3)),
                      coef_var=np.ones(n_factors), faces=np.array([[0, 1, 2], [0, 1, 3]]))


def test_session_whose_coefficients_do_not_fit_the_model_is_refused_whole(tmp_path):
    """Before: three Qt-slot tracebacks, then the error; now one error naming the session,
    raised before any of it is applied (the GUI's session controller reads through it)."""
    from app.model.controllers import SessionController
    from core.io import save_model

    save_model(tmp_path / "m.npz", _model(3))
    sessions.save_session(tmp_path / "s.json", Session(model=tmp_path / "m.npz",
                                                       points=[[1.0, 2, 3]], coef=[0.1] * 5))
    with pytest.raises(DataFileError, match="s.json: the session holds 5 shape coefficients "
                                            "but the model has 3 factors"):
        SessionController.read(tmp_path / "s.json")
    sessions.check_session_model(Session(coef=[0.1] * 3), _model(3), tmp_path / "s.json")


def test_zombie_recovery_writer_is_recognised_as_ended(state_dir, recovery):
    """Before: os.kill(pid, 0) succeeds on a zombie, so the crashed run was never offered."""
    code = ("import os, time\nfrom core.session import document as s\n"
            "from core.session.recovery import CrashRecovery\nr = CrashRecovery()\n"
            "r.write(s.Session(points=[[4.0, 5.0, 6.0]]))\nos._exit(3)\n")
    env = dict(os.environ, SSM_STUDIO_STATE_DIR=str(state_dir))
    child = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env)
    try:
        deadline = time.monotonic() + 30
        while Path(f"/proc/{child.pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
            assert time.monotonic() < deadline, "the child did not end"
            time.sleep(0.02)
        # its other threads may still be ending (holding the files) for a moment
        while not rec.previous_run_crashed():
            assert time.monotonic() < deadline, "a zombie writer was taken for running"
            time.sleep(0.02)
        os.kill(child.pid, 0)  # the pid still "exists": it is a zombie, not reaped
        np.testing.assert_array_equal(recovery.read().points, [[4.0, 5.0, 6.0]])
    finally:
        child.wait()


def test_reused_pid_does_not_hide_a_crashed_run(state_dir, recovery):
    """A recovery file whose writer ended, and whose pid now belongs to another process
    (checked by the start time the writer recorded): offered (before: suppressed)."""
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        own = recovery.write(Session(points=[[7.0, 8.0, 9.0]]))
        doc = json.loads(own.read_text())
        doc["writer"]["pid"] = other.pid
        doc["writer"]["created"] -= 1000  # the writer started before the process now there
        target = state_dir / f"recovery-{other.pid}-a.json"
        target.write_text(json.dumps(doc))
        own.unlink()
        assert rec.previous_run_crashed()
        np.testing.assert_array_equal(recovery.read().points, [[7.0, 8.0, 9.0]])
    finally:
        other.kill()
        other.wait()


def _as_written_by(recovery, state_dir: Path, pid: int, **writer) -> Path:
    """This process's autosave, rewritten as if ``pid`` had written it without a lock file."""
    own = recovery.write(Session(points=[[7.0, 8.0, 9.0]]))
    doc = json.loads(own.read_text())
    doc["writer"].update(pid=pid, **writer)
    for key in [k for k, v in writer.items() if v is None]:
        del doc["writer"][key]
    target = state_dir / f"recovery-{pid}-a.json"
    target.write_text(json.dumps(doc))
    own.unlink()
    return target


def test_writer_with_its_recorded_create_time_is_running(state_dir, recovery):
    """The pid-reuse check itself: the process whose creation time is the one recorded is
    the writer (not offered), the same pid with another time is not (offered)."""
    import psutil

    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        created = psutil.Process(other.pid).create_time()
        _as_written_by(recovery, state_dir, other.pid, created=created)
        assert not (state_dir / f"recovery-{other.pid}.lock").exists()  # psutil decides
        assert rec.writer_running(other.pid, created, state_dir)
        assert not rec.previous_run_crashed() and recovery.read() is None
        assert not rec.writer_running(other.pid, created - 5.0, state_dir)
        assert not rec.writer_running(other.pid, created + 5.0, state_dir)
    finally:
        other.kill()
        other.wait()
    assert not rec.writer_running(other.pid, created, state_dir)  # reaped: no such process
    np.testing.assert_array_equal(recovery.read().points, [[7.0, 8.0, 9.0]])


def test_file_from_before_psutil_is_judged_by_pid(state_dir, recovery):
    """A recovery file of the previous version records ``started`` in clock ticks, not a
    creation time: a live pid keeps it (not offered), an ended one has it offered."""
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        _as_written_by(recovery, state_dir, other.pid, created=None, started=123456)
        assert not rec.previous_run_crashed()
    finally:
        other.kill()
        other.wait()
    assert rec.previous_run_crashed()
    np.testing.assert_array_equal(recovery.read().points, [[7.0, 8.0, 9.0]])


def test_left_over_unlocked_lock_file_does_not_hide_a_crash(state_dir, recovery):
    """filelock leaves the lock file in place; one nobody holds means its writer ended, even
    when the pid is alive again (reused), and it is removed when read."""
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        _as_written_by(recovery, state_dir, other.pid)
        (state_dir / f"recovery-{other.pid}.lock").write_bytes(b"")
        assert rec.previous_run_crashed()
        assert not (state_dir / f"recovery-{other.pid}.lock").exists()
    finally:
        other.kill()
        other.wait()


def test_two_autosaves_keep_their_own_state(tmp_path):
    """No module state: two CrashRecovery objects in other folders alternate their own slots,
    and clearing one leaves the other's file and lock."""
    first, second = rec.CrashRecovery(tmp_path / "one"), rec.CrashRecovery(tmp_path / "two")
    try:
        a1 = first.write(Session(points=[[1.0, 1.0, 1.0]]))
        b1 = second.write(Session(points=[[2.0, 2.0, 2.0]]))
        a2 = first.write(Session(points=[[3.0, 3.0, 3.0]]))
        assert (a1.parent, b1.parent) == (tmp_path / "one", tmp_path / "two")
        assert a1.name.endswith("-a.json") and a2.name.endswith("-b.json") and first.path == a2
        first.clear()
        assert list((tmp_path / "one").iterdir()) == []
        assert sorted(p.name for p in (tmp_path / "two").iterdir()) == \
            [f"recovery-{os.getpid()}-a.json", f"recovery-{os.getpid()}.lock"]
        np.testing.assert_array_equal(sessions.load_session(second.path).points, [[2.0, 2.0, 2.0]])
    finally:
        first.clear()
        second.clear()


def test_running_writer_holds_its_lock(state_dir):
    """A live instance (lock held) is not offered, even when its files look old."""
    code = ("import sys, time\nfrom core.session import document as s\n"
            "from core.session.recovery import CrashRecovery\nr = CrashRecovery()\n"
            "r.write(s.Session(points=[[1.0, 1.0, 1.0]]))\nprint('ready', flush=True)\n"
            "sys.stdin.readline()\n")
    env = dict(os.environ, SSM_STUDIO_STATE_DIR=str(state_dir))
    child = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env, text=True,
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert child.stdout.readline().strip() == "ready"
        assert (state_dir / f"recovery-{child.pid}.lock").exists()
        assert not rec.previous_run_crashed()
    finally:
        child.kill()
        child.wait()
    assert rec.previous_run_crashed()  # killed: the lock went with it


def test_recovered_session_that_does_not_fit_its_model_is_refused(state_dir, tmp_path):
    from app.model.controllers import SessionController
    from app.model.state import WorkspaceState
    from core.io import save_model

    save_model(tmp_path / "m.npz", _model(3))
    crashing_run(state_dir=state_dir, script=f"""
r.write(s.Session(model={str(tmp_path / 'm.npz')!r}, points=[[1.0, 2.0, 3.0]],
                  coef=[0.5] * 4))""")
    with pytest.raises(DataFileError, match="holds 4 shape coefficients but the model has 3"):
        SessionController(WorkspaceState()).pending_recovery()
    assert not rec.previous_run_crashed()  # discarded, not offered again
