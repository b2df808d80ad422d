"""The model library: structure descriptions in model headers, library folders, shipped models."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from core.io import load_model, save_model
from core.io.model_library import (
    MNI_TEMPLATE_SPACE,
    RESOURCES_MODELS,
    StructureInfo,
    list_library,
    structure_info,
    user_models_dir,
    with_structure,
)
from core.models.shape_model import ShapeModel
from core.planning.frames import volume_centroid


def _tiny_model(info=None) -> ShapeModel:
    mean = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return ShapeModel(mean, np.zeros((1, 4, 3)) + 0.1, np.ones(1), faces, info=info or {})


def test_structure_info_round_trips_through_the_model_file(tmp_path):
    info = StructureInfo("thalamus", "right", (0.1, 0.5, 0.2), MNI_TEMPLATE_SPACE, demo=True,
                         target=(1.0, 2.0, 3.0))
    path = tmp_path / "m.npz"
    save_model(path, with_structure(_tiny_model(), info))
    assert structure_info(load_model(path)) == info
    assert info.label == "Right thalamus (demo)"


def test_older_files_get_a_structure_from_their_name(tmp_path):
    assert structure_info(_tiny_model({"structure": "left caudate nucleus"})) == StructureInfo(
        "caudate nucleus", "left", structure_info(_tiny_model(), "x_caudate.npz").color)
    guessed = structure_info(_tiny_model(), tmp_path / "Right-Putamen.npz")
    assert (guessed.name, guessed.side) == ("Putamen", "right")
    assert structure_info(_tiny_model()).name == "structure"


@pytest.mark.parametrize("kwargs, message", [
    ({"side": "up"}, "side"), ({"color": (2, 0, 0)}, "colour"), ({"target": (1, 2)}, "target")])
def test_bad_structure_descriptions_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        StructureInfo("x", **kwargs)


def test_library_lists_user_models_and_reports_bad_files(tmp_path, monkeypatch):
    monkeypatch.setenv("SSM_STUDIO_DATA_DIR", str(tmp_path))
    folder = user_models_dir()
    assert folder == tmp_path / "models"
    folder.mkdir()
    save_model(folder / "mine.npz", with_structure(_tiny_model(), StructureInfo("pallidum", "left")))
    (folder / "broken.npz").write_bytes(b"PK\x03\x04 not really")
    (folder / ".hidden.npz").write_bytes(b"")
    (folder / "notes.txt").write_text("x")
    entries = list_library([folder])
    assert [e.path.name for e in entries] == ["mine.npz", "broken.npz"]
    assert entries[0].structure.label == "Left pallidum" and entries[0].n_vertices == 4
    assert "broken.npz" in entries[1].error and entries[1].structure is None


def test_user_models_dir_defaults(tmp_path, monkeypatch):
    """Without SSM_STUDIO_DATA_DIR: the XDG data folder, else ~/.local/share (Linux)."""
    if sys.platform != "linux":
        pytest.skip("the XDG defaults are Linux's")
    monkeypatch.delenv("SSM_STUDIO_DATA_DIR", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert user_models_dir() == tmp_path / "xdg" / "ssm-studio" / "models"
    monkeypatch.delenv("XDG_DATA_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert user_models_dir() == tmp_path / "home" / ".local" / "share" / "ssm-studio" / "models"


def test_shipped_library_models_sit_on_their_side_of_the_symmetric_template():
    entries = {e.path.name: e for e in list_library([RESOURCES_MODELS])}
    assert {"left_caudate.npz", "right_caudate.npz"} <= set(entries)
    centroids = {}
    for name, entry in entries.items():
        assert not entry.error
        assert entry.structure.demo and entry.structure.template_space == MNI_TEMPLATE_SPACE
        model = load_model(entry.path)
        world = model.world_instance()
        centroids[name] = volume_centroid(world, model.faces)
        side = entry.structure.side
        assert (centroids[name][0] < 0) == (side == "left"), name
    for left, right in (("left_caudate.npz", "right_caudate.npz"),
                        ("left_thalamus.npz", "right_thalamus.npz")):
        if left in centroids and right in centroids:
            mirrored = centroids[right] * [-1, 1, 1]
            # the MNI 2009a template is left-right symmetric: the two models are built from
            # mirror-image base shapes but independent synthetic populations
            assert np.linalg.norm(mirrored - centroids[left]) < 1.5, (left, right)
