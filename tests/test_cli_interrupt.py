"""Ctrl-C and SIGTERM stop a batch command promptly, also when started with SIGINT ignored."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

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


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_correspond_stops_on_a_signal_with_its_exit_code(tmp_path, sig, code):
    meshes = sorted((ROOT / "resources" / "demo" / "meshes").glob("*.vtk"))[:6]
    if len(meshes) < 6:
        pytest.skip("demo meshes missing")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    # a job runner's background job: SIGINT starts out ignored (as bash does for `cmd &`)
    proc = subprocess.Popen(
        [sys.executable, "-m", "core.cli", "correspond", *map(str, meshes), "--reference",
         "auto", "--out", str(tmp_path / "out")], env=env, stdout=subprocess.DEVNULL,
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
    assert "Traceback" not in err.decode()
