"""Ctrl-C and SIGTERM stop a batch command promptly, also when started with SIGINT ignored;
``correspond`` leaves every finished output and a report of what completed (issue 18 item 14)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
from proc_tree import descendants, session_members, still_alive

ROOT = Path(__file__).resolve().parents[1]


def _wait_for_progress(proc: subprocess.Popen, timeout: float = 120.0) -> bytes:
    """The stderr bytes up to the command's first progress bar (its work has started: the
    imports before it can take seconds on a loaded machine, and a signal sent then is not
    the case under test). Fails if the command ends or shows no progress in time."""
    import select

    seen = b""
    deadline = time.monotonic() + timeout
    fd = proc.stderr.fileno()
    while b"[" not in seen:
        if proc.poll() is not None or time.monotonic() > deadline:
            pytest.fail(f"no progress from the command: {seen[-500:]!r}")
        ready, _, _ = select.select([fd], [], [], 0.2)
        if ready:
            seen += os.read(fd, 4096)
    return seen


def _wait_for(condition, proc: subprocess.Popen, guard: float = 60.0) -> None:
    """Until ``condition()`` holds (a hang guard, not a timing assertion)."""
    deadline = time.monotonic() + guard
    while time.monotonic() < deadline and not condition() and proc.poll() is None:
        time.sleep(0.05)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_correspond_stops_on_a_signal_with_its_exit_code(tmp_path, sig, code):
    meshes = sorted((ROOT / "resources" / "demo" / "meshes").glob("*.vtk"))[:6]
    if len(meshes) < 6:
        pytest.skip("demo meshes missing")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = tmp_path / "out"
    # a job runner's background job: SIGINT starts out ignored (as bash does for `cmd &`)
    proc = subprocess.Popen(
        [sys.executable, "-m", "core.cli", "correspond", *map(str, meshes), "--reference",
         "auto", "--out", str(out)], env=env, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))
    head = _wait_for_progress(proc)  # into the work (the demo batch takes far longer)
    assert proc.poll() is None
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=10)
        err = head + err
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"correspond did not stop within 10 s of {sig.name}")
    assert proc.returncode == code
    text = err.decode(errors="replace")
    assert "Traceback" not in text and "leaked" not in text, text[-4000:]
    report = json.loads((out / "correspondence.json").read_text())
    assert report["interrupted"] == sig.name and report["complete"] is False


def test_sigint_to_correspond_leaves_finished_shapes_and_a_report(tmp_path):
    """SIGINT to one `correspond --jobs 2` process while its workers stream outputs: exit 130,
    no traceback, the report lists the finished outputs, each reads back whole, no worker
    (nor fork server) survives."""
    from core.datasets.shapes import known_homology_shapes
    from core.io import load_mesh, save_mesh

    population = known_homology_shapes("bean", 20, seed=5, n_points=(90, 120))
    paths = []
    for mesh in population.meshes:
        paths.append(tmp_path / f"{mesh.name}.vtk")
        save_mesh(paths[-1], mesh)
    # the command's own temporary folder: short, since the fork server's socket lives in it
    # (AF_UNIX paths are limited to 107 bytes; pytest-xdist's tmp_path is longer)
    out, temp = tmp_path / "out", Path(tempfile.mkdtemp(prefix="ssm-t-"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "core.cli", "correspond", *map(str, paths), "--reference",
         str(paths[0]), "--out", str(out), "--jobs", "2", "--max-iterations", "30"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(temp)))
    try:
        _wait_for(lambda: any(out.glob("bean_*.vtk")), proc)  # outputs arrive as they finish
        workers = descendants(proc.pid)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)  # a hang guard
    finally:
        proc.kill()
        left = list(temp.iterdir())
        shutil.rmtree(temp, ignore_errors=True)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "leaked" not in err and "stopped by SIGINT" in err
    report = json.loads((out / "correspondence.json").read_text())
    assert report["interrupted"] == "SIGINT" and report["complete"] is False
    done = [s["output"] for s in report["shapes"] if s["output"]]
    assert 1 <= len(done) < len(paths) == len(report["shapes"])
    assert sorted(Path(p).name for p in done) == sorted(p.name for p in out.glob("bean_*.vtk"))
    first = load_mesh(done[0])
    for path in done:  # every reported output is a whole mesh in the common topology
        mesh = load_mesh(path)
        assert mesh.vertices.shape == first.vertices.shape
        assert (mesh.faces == first.faces).all()
    # the others are left as their reference-based results, in provisional/
    for shape in report["shapes"]:
        assert (shape["output"] is None) != (shape["provisional"] is None), shape
    provisional = [s["provisional"] for s in report["shapes"] if s["provisional"]]
    assert report["n_provisional"] == len(provisional) == len(paths) - len(done)
    for path in provisional:
        assert Path(path).parent == out / "provisional"
        mesh = load_mesh(path)
        assert mesh.vertices.shape == first.vertices.shape and (mesh.faces == first.faces).all()
    assert len(workers) >= 2
    assert still_alive(workers) == []
    # nor its temporary folder (multiprocessing's pymp-*, the fork server's socket in it)
    assert left == []


def test_a_killed_command_leaves_no_worker_or_fork_server(tmp_path):
    """SIGKILL cannot be handled: the workers die with the fork server, and the server (and
    the resource tracker) with the command."""
    meshes = sorted((ROOT / "resources" / "demo" / "meshes").glob("*.vtk"))[:6]
    if len(meshes) < 6:
        pytest.skip("demo meshes missing")
    # a killed process cannot remove its temporary folder (the fork server's socket): the
    # test gives it one of its own (short: AF_UNIX paths) and removes it
    temp = Path(tempfile.mkdtemp(prefix="ssm-t-"))
    env = dict(os.environ, PYTHONPATH=str(ROOT), TMPDIR=str(temp))
    proc = subprocess.Popen(
        [sys.executable, "-m", "core.cli", "correspond", *map(str, meshes), "--jobs", "2",
         "--out", str(tmp_path / "out")], env=env, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, start_new_session=True)
    _wait_for_progress(proc)

    def session() -> list[int]:
        return [pid for pid in session_members(proc.pid) if pid != proc.pid]

    deadline = time.monotonic() + 60
    while len(session()) < 2 and time.monotonic() < deadline:   # the server and a worker
        time.sleep(0.2)
    assert len(session()) >= 2
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 20
    while session() and time.monotonic() < deadline:
        time.sleep(0.2)
    shutil.rmtree(temp, ignore_errors=True)
    assert session() == []


def test_a_reading_child_dies_with_its_parent(tmp_path):
    """An input is read in a child process (a reader crash costs that file only); when the
    reading process dies (a pool worker terminated mid-read, a SIGKILLed command), its child
    goes too -- an orphan would block forever writing a mesh into the pipe, holding the
    command's stderr open."""
    import numpy as np

    from core.io import TriMesh, save_mesh

    rng = np.random.default_rng(0)
    vertices = rng.normal(size=(30000, 3))  # a message far larger than a pipe's buffer
    save_mesh(tmp_path / "big.vtk", TriMesh(vertices, rng.integers(0, 30000, (60000, 3))))
    script = ("import sys\nfrom core.io import load_meshes\n"
              "load_meshes([sys.argv[1]] * 200, isolate=True)\n")
    proc = subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "big.vtk")],
                            env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    children: set[int] = set()
    try:
        _wait_for(lambda: descendants(proc.pid), proc)
        children = descendants(proc.pid)
        assert children, "the reader never started a child"
        proc.kill()
        proc.wait()
        assert still_alive(children, guard=20.0) == []
    finally:
        proc.kill()
        for pid in still_alive(children, guard=0.0):  # a failed run leaves no orphan behind
            os.kill(pid, signal.SIGKILL)
