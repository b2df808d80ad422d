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
    time.sleep(2.0)  # into the work (the demo batch takes far longer than this)
    assert proc.poll() is None
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"correspond did not stop within 10 s of {sig.name}")
    assert proc.returncode == code
    assert "Traceback" not in err.decode()
