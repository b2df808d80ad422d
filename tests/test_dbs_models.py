"""The DBS target models of the library (CIT168-derived, resources/models) and the ventricles."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.geometry.mesh import is_closed
from core.geometry.mesh import volume as mesh_volume
from core.geometry.toolkit import signed_surface_distance, winding_numbers
from core.io import load_mesh, load_model, load_volume
from core.io.model_library import StructureInfo, list_library, structure_info
from core.planning.frames import VENTRICLES_FILE

RESOURCES = Path(__file__).resolve().parents[1] / "resources"
STEMS = {"stn": "subthalamic nucleus", "gpi": "globus pallidus internus",
         "gpe": "globus pallidus externus", "rn": "red nucleus",
         "snr": "substantia nigra pars reticulata"}
# CIT168 label centroids (MNI152NLin2009cAsym mm, measured on the atlas's label map) moved by
# the measured (0, 0, -1) mm onto the demo template.
ATLAS_CENTROIDS = {"left_stn": (-11.1, -12.7, -8.6), "right_stn": (10.8, -11.9, -8.7),
                   "left_gpi": (-17.5, -5.2, -5.5), "left_rn": (-5.2, -19.4, -10.4)}


def _built():
    return sorted(p.stem for p in (RESOURCES / "models").glob("*.npz")
                  if p.stem.split("_", 1)[1] in STEMS)


def test_library_lists_every_dbs_model_with_its_header():
    entries = {e.path.stem: e for e in list_library([RESOURCES / "models"])}
    assert {"left_stn", "right_stn", "left_gpi", "right_gpi", "left_gpe", "right_gpe",
            "left_rn", "right_rn"} <= set(entries)
    for stem in _built():
        info = entries[stem].structure
        side, key = stem.split("_", 1)
        assert entries[stem].error == ""
        assert (info.name, info.side, info.demo) == (STEMS[key], side, True)
        assert info.template_space == "MNI152NLin2009aSym"
        assert info.source_space == "MNI152NLin2009cAsym"
        assert info.target is not None and info.target_name
        assert info.label.endswith("(demo)")
        model = load_model(entries[stem].path)
        atlas = model.info["atlas"]
        assert "Pauli" in atlas["atlas"] and "CC BY 4.0" in atlas["atlas"]
        assert atlas["atlas_to_template"]["translation_mm"] == [0.0, 0.0, -1.0]
        assert atlas["atlas_to_template"]["residual_mm"] < 1.5


@pytest.mark.parametrize("stem", sorted(ATLAS_CENTROIDS))
def test_models_sit_where_the_atlas_puts_the_structure(stem):
    model = load_model(RESOURCES / "models" / f"{stem}.npz")
    centroid = model.world_instance().mean(axis=0)
    assert np.linalg.norm(centroid - ATLAS_CENTROIDS[stem]) < 1.0


def test_targets_lie_inside_in_their_clinical_part():
    for stem in _built():
        model = load_model(RESOURCES / "models" / f"{stem}.npz")
        target = np.asarray(structure_info(model).target)
        assert signed_surface_distance(target, model.mean, model.faces)[0] < -0.3, stem
    for side, sign in (("left", -1), ("right", 1)):
        stn = load_model(RESOURCES / "models" / f"{side}_stn.npz")
        world_target = stn.to_world(np.asarray(structure_info(stn).target)[None])[0]
        centre = stn.world_instance().mean(axis=0)
        # dorsolateral: more lateral and higher than the centroid
        assert sign * (world_target[0] - centre[0]) > 0.5 and world_target[2] - centre[2] > 0.5
        gpi = load_model(RESOURCES / "models" / f"{side}_gpi.npz")
        world_target = gpi.to_world(np.asarray(structure_info(gpi).target)[None])[0]
        centre = gpi.world_instance().mean(axis=0)
        # posterolateral: more lateral and more posterior
        assert sign * (world_target[0] - centre[0]) > 0.5 and world_target[1] - centre[1] < -0.5


def test_structure_info_keeps_older_headers_as_they_were():
    old = {"name": "caudate nucleus", "side": "left", "color": [0.2, 0.6, 0.2],
           "template_space": "MNI152NLin2009aSym", "demo": True}
    info = StructureInfo.from_dict(old)
    assert info.target_name == "" and info.source_space == ""
    assert info.to_dict() == old
    new = StructureInfo.from_dict({**old, "target": [1, 2, 3], "target_name": "x",
                                   "source_space": "MNI152NLin2009cAsym"})
    assert StructureInfo.from_dict(new.to_dict()) == new


def test_ventricles_are_the_templates_csf_spaces():
    mesh = load_mesh(VENTRICLES_FILE)
    assert is_closed(mesh.faces)
    assert 15_000 < mesh_volume(mesh.vertices, mesh.faces) < 20_000     # mm^3
    gm = load_volume(RESOURCES / "mni_icbm152_gm_tal_nlin_sym_09a.nii.gz")
    wm = load_volume(RESOURCES / "mni_icbm152_wm_tal_nlin_sym_09a.nii.gz")
    lo, hi = np.floor(mesh.vertices.min(0)), np.ceil(mesh.vertices.max(0))
    rng = np.random.default_rng(0)
    probe = rng.uniform(lo, hi, size=(600, 3))
    inside = winding_numbers(probe, mesh.vertices, mesh.faces) > 0.5
    ijk = np.rint(gm.world_to_voxel(probe)).astype(int)
    csf = 1 - (gm.data[tuple(ijk.T)].astype(float) + wm.data[tuple(ijk.T)]) / 255
    assert csf[inside].mean() > 0.6 and csf[~inside].mean() < 0.3
