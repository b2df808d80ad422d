"""core.planning.measure: ruler and angle values, session JSON, CSV and Slicer markups files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.planning.measure import (
    Measurement,
    measurements_from_json,
    measurements_to_json,
    save_measurements,
)


def test_values_of_known_rulers_and_angles():
    assert Measurement("ruler", [[0, 0, 0], [3, 4, 0]]).value == pytest.approx(5.0)
    assert Measurement("angle", [[5, 0, 0], [0, 0, 0], [0, 2, 0]]).value == pytest.approx(90.0)
    rng = np.random.default_rng(1)
    for _ in range(5):
        b = rng.normal(0, 10, 3)
        theta = rng.uniform(0.1, np.pi - 0.1)
        u = rng.standard_normal(3)
        u /= np.linalg.norm(u)
        w = np.cross(u, rng.standard_normal(3))
        w /= np.linalg.norm(w)
        a, c = b + 3 * u, b + 7 * (np.cos(theta) * u + np.sin(theta) * w)
        assert Measurement("angle", [a, b, c]).value == pytest.approx(np.degrees(theta))
    assert Measurement("ruler", [[0, 0, 0], [1, 0, 0]]).label() == "1.0 mm"
    with pytest.raises(ValueError, match="a ruler needs 2 finite 3D points, got 3"):
        Measurement("ruler", np.zeros((3, 3)))
    with pytest.raises(ValueError, match="measurement must be one of"):
        Measurement("area", np.zeros((2, 3)))


def test_session_round_trip_and_files(tmp_path):
    items = [Measurement("ruler", [[1, 2, 3], [4, 6, 3]], "axial", 3.0),
             Measurement("angle", [[1, 0, 0], [0, 0, 0], [0, 1, 0]], "coronal", 0.0)]
    back = measurements_from_json(json.loads(json.dumps(measurements_to_json(items))))
    assert [(m.kind, m.frame, m.depth) for m in back] == [("ruler", "axial", 3.0),
                                                          ("angle", "coronal", 0.0)]
    np.testing.assert_array_equal(back[0].points, items[0].points)
    with pytest.raises(ValueError, match="measurement 1: "):
        measurements_from_json([{"kind": "ruler", "points": [[0, 0, 0]]}])
    csv = save_measurements(tmp_path / "m.csv", items).read_text().splitlines()
    assert csv[0].startswith("kind,value,unit") and len(csv) == 3
    assert csv[1].split(",")[:3] == ["ruler", "5.0000", "mm"]
    assert csv[2].split(",")[:3] == ["angle", "90.0000", "deg"]
    doc = json.loads(save_measurements(tmp_path / "m.mrk.json", items).read_text())
    line, angle = doc["markups"]
    assert line["type"] == "Line" and angle["type"] == "Angle"
    assert line["coordinateSystem"] == "LPS"
    assert line["controlPoints"][0]["position"] == [-1.0, -2.0, 3.0]   # RAS -> LPS
    assert line["measurements"][0]["value"] == pytest.approx(5.0)
    with pytest.raises(ValueError, match="written as .csv or .mrk.json"):
        save_measurements(tmp_path / "m.txt", items)
