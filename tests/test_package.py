"""Packaging and layout rules: the CLI answers, and core/ never imports Qt."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import core

ROOT = Path(__file__).resolve().parents[1]
QT_MODULES = {"PySide6", "PyQt5", "PyQt6", "pyvistaqt", "qtpy", "app"}


def test_core_never_imports_qt_or_app():
    offenders = []
    for path in (ROOT / "core").rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            offenders += [f"{path.relative_to(ROOT)}: {n}" for n in names
                          if n.split(".")[0] in QT_MODULES]
    assert offenders == []


def test_version_and_help():
    out = subprocess.run([sys.executable, "-m", "app.main", "--version"], capture_output=True,
                         text=True, cwd=ROOT)
    assert out.returncode == 0 and out.stdout.strip() == f"ssm-studio {core.__version__}"
    out = subprocess.run([sys.executable, "-m", "app.main", "--help"], capture_output=True,
                         text=True, cwd=ROOT)
    assert out.returncode == 0 and "--screenshot" in out.stdout and "view" in out.stdout


def test_engine_commands_do_not_import_qt():
    code = ("import sys; from app.main import build_parser; build_parser(); "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('PySide6', 'pyvistaqt')]; "
            "print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stdout + out.stderr


def test_a_command_imports_only_its_own_module(tmp_path):
    """``ssm-studio mesh-labels`` (or any engine command) loads that command, not the other
    commands nor the whole of VTK: both cost about a second of start-up. The help listing still
    shows every command."""
    import nibabel as nib
    import numpy as np

    labels = np.zeros((12, 12, 12), np.uint8)
    labels[3:9, 4:8, 3:9] = 5
    nib.save(nib.Nifti1Image(labels, np.eye(4)), tmp_path / "labels.nii.gz")
    code = ("import sys; from app.main import main; "
            f"code = main(['mesh-labels', {str(tmp_path / 'labels.nii.gz')!r}, '--label', '5', "
            f"'--vertices', '60', '--out', {str(tmp_path / 'out')!r}]); "
            "loaded = [m for m in ('vtk', 'core.cli.correspond', 'core.cli.evaluate', 'PySide6') "
            "if m in sys.modules]; print(loaded); sys.exit(code or (1 if loaded else 0))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    assert len(list((tmp_path / "out").glob("*.vtk"))) == 1
    for program in (["app.main"], ["core.cli"]):
        listing = subprocess.run([sys.executable, "-m", *program, "--help"], capture_output=True,
                                 text=True, cwd=ROOT).stdout
        assert all(name in listing for name in ("mesh-labels", "correspond", "register-images"))


def _code_lines(node: ast.FunctionDef) -> int:
    """Lines of a function without its docstring."""
    lines = node.end_lineno - node.lineno + 1
    first = node.body[0] if node.body else None
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and \
            isinstance(first.value.value, str):
        lines -= first.end_lineno - first.lineno + 1
    return lines


def test_no_function_in_core_is_longer_than_80_lines_of_code():
    """Issue 16: the largest function in core/ stays under ~80 lines (docstrings aside)."""
    long = []
    for path in (ROOT / "core").rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _code_lines(node) > 80:
                long.append(f"{path.relative_to(ROOT)}: {node.name} ({_code_lines(node)} lines)")
    assert long == []
