"""The fuzz corpus (tests/fuzz_corpus.py): every damaged input refused cleanly by every reader
and CLI command: no crash, no traceback, no silent accept, every message naming the file.

The readers run in one child process (tests/fuzz_run.py), so that a native crash in a
reader is reported as the case that was being read instead of ending the test run. The CLI
commands run in-process (their batch readers isolate native readers in child processes
themselves); each must exit with an error code and print one-line messages naming the file.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import fuzz_corpus  # noqa: E402

from core.cli import main as cli_main  # noqa: E402
from core.errors import display_path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> list[fuzz_corpus.Case]:
    return fuzz_corpus.generate(tmp_path_factory.mktemp("fuzz"))


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict:
    return fuzz_corpus.good_files(tmp_path_factory.mktemp("good"))


def _run_readers(cases: list[fuzz_corpus.Case], folder: Path) -> dict[int, dict]:
    """Results by case index; a case during which the child died gets status 'crashed'."""
    results: dict[int, dict] = {}
    todo = list(range(len(cases)))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    while todo:
        listing = folder / "cases.json"
        listing.write_text(json.dumps([[str(cases[i].path), cases[i].kind] for i in todo]))
        proc = subprocess.run([sys.executable, str(ROOT / "tests" / "fuzz_run.py"),
                               str(listing)], capture_output=True, text=True, env=env,
                              timeout=300)
        started = None
        for line in proc.stdout.splitlines():
            record = json.loads(line)
            if "start" in record:
                started = todo[record["start"]]
            else:
                results[todo[record["index"]]] = record
        if proc.stderr.strip():
            results.setdefault(-1, {"stderr": ""})["stderr"] += proc.stderr
        if proc.returncode == 0:
            break
        crashed = started if started is not None else todo[0]
        results[crashed] = {"status": "crashed", "message": f"exit {proc.returncode}"}
        todo = todo[todo.index(crashed) + 1:]
    return results


def test_corpus_is_large_and_covers_every_reader(corpus):
    assert len(corpus) >= 200
    kinds = {c.kind for c in corpus}
    assert kinds == set(fuzz_corpus.KINDS)
    suffixes = {c.path.name.split(".", 1)[1] for c in corpus}
    for suffix in ("vtk", "vtp", "vtu", "stl", "ply", "obj", "gii", "gii.gz", "nii", "nii.gz",
                   "csv", "tsv", "fcsv", "mrk.json", "json", "npz"):
        assert suffix in suffixes, suffix


def test_every_reader_refuses_every_damaged_input(corpus, tmp_path):
    results = _run_readers(corpus, tmp_path)
    assert "stderr" not in results.get(-1, {}), results[-1]["stderr"][-2000:]  # nothing leaks
    problems = []
    for index, case in enumerate(corpus):
        result = results.get(index, {"status": "missing"})
        message = result.get("message", "")
        if result["status"] != "refused":
            problems.append(f"{case.name} ({case.damage}): {result['status']} {message[:150]}")
        elif not message.startswith(display_path(case.path)) or "\n" in message:
            problems.append(f"{case.name}: message does not start with the file: {message!r}")
        for warning in result.get("warnings", []):
            if case.path.name not in warning:
                problems.append(f"{case.name}: warning without the file name: {warning!r}")
    assert not problems, f"{len(problems)} of {len(corpus)} cases:\n" + "\n".join(problems)


def _cli(argv: list[str], capsys) -> tuple[int, list[str]]:
    code = cli_main(argv)
    captured = capsys.readouterr()
    lines = [ln for ln in captured.err.splitlines() if ln.strip() and "\r" not in ln
             and "[#" not in ln and "[-" not in ln]
    return code, lines


def _cli_problems(name: str, bad: Path, code: int, lines: list[str], codes=(1, 2)) -> list[str]:
    problems = []
    text = "\n".join(lines)
    if code not in codes:
        problems.append(f"{name}: exit code {code}")
    if "Traceback" in text:
        problems.append(f"{name}: traceback")
    if bad.name not in text:
        problems.append(f"{name}: no message names {bad.name}: {text[:200]!r}")
    for line in lines:
        if not line.startswith("ssm-studio ") and not line.startswith("skipped "):
            problems.append(f"{name}: not a one-line message: {line[:120]!r}")
    return problems


def _pick(corpus, kind: str, every: int = 1) -> list[fuzz_corpus.Case]:
    chosen = [c for c in corpus if c.kind == kind]
    return chosen[::every]


def test_cli_fit_and_segment_refuse_damaged_inputs(corpus, good, tmp_path, capsys):
    problems = []
    out = tmp_path / "out"
    for case in _pick(corpus, "model"):
        code, lines = _cli(["fit", "--model", str(case.path), "--points", str(good["points"]),
                            "--out", str(out / "fit.vtk")], capsys)
        problems += _cli_problems(f"fit --model {case.name}", case.path, code, lines)
    for case in _pick(corpus, "points"):
        code, lines = _cli(["fit", "--model", str(good["model"]), "--points", str(case.path),
                            "--out", str(out / "fit.vtk")], capsys)
        problems += _cli_problems(f"fit --points {case.name}", case.path, code, lines)
    for case in _pick(corpus, "volume"):
        code, lines = _cli(["segment", "--model", str(good["model"]), "--points",
                            str(good["points"]), "--image", str(case.path),
                            "--out", str(out / "mask.nii.gz")], capsys)
        problems += _cli_problems(f"segment --image {case.name}", case.path, code, lines)
    assert not problems, "\n".join(problems)


def test_cli_align_refuses_damaged_meshes(corpus, good, tmp_path, capsys):
    problems = []
    meshes = [str(p) for p in good["meshes"]]
    for case in _pick(corpus, "mesh")[::5]:  # all of them go through the readers above
        code, lines = _cli(["align", *meshes, str(case.path), "--out", str(tmp_path / "a")],
                           capsys)
        problems += _cli_problems(f"align {case.name}", case.path, code, lines, codes=(1,))
    assert not problems, "\n".join(problems)


def test_cli_build_and_convert_refuse_damaged_inputs(corpus, good, tmp_path, capsys):
    problems = []
    meshes = [str(p) for p in good["meshes"]]
    for case in _pick(corpus, "mesh")[2::14]:
        code, lines = _cli(["build-model", *meshes, str(case.path), "--method", "pca",
                            "--out", str(tmp_path / "m.npz")], capsys)
        problems += _cli_problems(f"build-model {case.name}", case.path, code, lines)
    for case in _pick(corpus, "model", every=3):
        code, lines = _cli(["convert-model", str(case.path), str(tmp_path / "c.npz")], capsys)
        problems += _cli_problems(f"convert-model {case.name}", case.path, code, lines)
    assert not problems, "\n".join(problems)


def test_cli_plan_refuses_damaged_sessions(corpus, tmp_path, capsys):
    if "plan" not in __import__("core.cli", fromlist=["command_modules"]).command_modules():
        pytest.skip("no plan command")
    problems = []
    for case in _pick(corpus, "session"):
        code, lines = _cli(["plan", "--session", str(case.path), "--out",
                            str(tmp_path / "plan.json")], capsys)
        problems += _cli_problems(f"plan --session {case.name}", case.path, code, lines)
    assert not problems, "\n".join(problems)


def test_cli_correspond_reports_a_damaged_mesh_and_goes_on(corpus, good, tmp_path, capsys):
    """One crashing-class file (a cell index past the points) among good ones: reported for
    that file, the others written (before: exit 139, no report)."""
    bad = next(c for c in corpus if c.name == "vtu_legacy_index_past_end").path
    meshes = [str(p) for p in good["meshes"]]
    code, lines = _cli(["correspond", *meshes, str(bad), "--out", str(tmp_path / "c"),
                        "--n-references", "1", "--jobs", "1", "--max-iterations", "5"], capsys)
    assert not _cli_problems("correspond", bad, code, lines, codes=(1,))
    report = json.loads((tmp_path / "c" / "correspondence.json").read_text())
    assert str(bad) in report["failures"]
    assert sum(1 for s in report["shapes"] if s["ok"]) == 3
