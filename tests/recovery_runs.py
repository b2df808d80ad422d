"""A run of SSM Studio's engine that autosaves for crash recovery and dies without cleaning up."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def crashing_run(script: str, *args: str, state_dir: Path | None = None) -> int:
    """Run ``script`` in a new Python process that ends by ``os._exit(3)`` (no clean exit,
    so its recovery files stay); its pid. The script has ``s`` (core.session.document),
    ``r`` (a core.session.recovery.CrashRecovery), ``np`` and ``sys.argv[1:] == args``."""
    code = ("import os, sys, numpy as np\nfrom core.session import document as s\n"
            "from core.session.recovery import CrashRecovery\nr = CrashRecovery()\n"
            + script + "\nos._exit(3)\n")
    env = dict(os.environ)
    if state_dir is not None:
        env["SSM_STUDIO_STATE_DIR"] = str(state_dir)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    proc = subprocess.Popen([sys.executable, "-c", code, *args], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 3, stderr
    return proc.pid
