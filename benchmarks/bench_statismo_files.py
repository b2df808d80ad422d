"""What SSM Studio does with each real statismo / Scalismo / scalismo-faces file.

For every file of ``../shared/data/real/statismo/`` (see its SOURCES.md; ``FILE#shape`` for
the scalismo-faces catalogs) one row: read or refused (the one-line message), vertices and
factors, how far the stored basis is from orthonormal (max |U'U - I|), the round trip
h5 -> npz -> h5 read back as a foreign file (no ``ssmstudio`` group: mean error and the
relative Frobenius gap of the world-shape covariances), and two fits with
``core.reconstruction.fit_points`` (gmm-aniso, similarity pose, 30 iterations) to noise-free
contour points in 5 slices: of the model's mean surface (the residual: mean point-to-surface
distance), and of a random shape of the model (coefficients ~ N(0, coef_var), seed 0: also
the mean vertex error against that known shape). Lengths in the file's units (mm).

Run: ``.venv/bin/python benchmarks/bench_statismo_files.py [--folder DIR]``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from core.evaluation.simulated_user import simulate_user  # noqa: E402
from core.io import DataFileError, load_model, save_model  # noqa: E402
from core.io.statismo import read_statismo  # noqa: E402
from core.models.shape_model import covariance_gap  # noqa: E402
from core.reconstruction import fit_points  # noqa: E402

FILES = ("RvtkStatismo_mandibles.h5", "scalismo_asmData_model.h5",
         "scalismo-faces_random-l4.h5", "scalismo-faces_random-l4.h5#shape",
         "scalismo-faces_random-momo.h5", "scalismo-faces_random-momo.h5#shape",
         "scalismo-faces_random-momo.h5#color", "scalismo_TetraMeshModel1.h5",
         "scalismo_TetraMeshModel2.h5")


def fit_to(model, vertices: np.ndarray) -> tuple[float, np.ndarray]:
    extent = float(np.ptp(vertices, axis=0).max())
    user = simulate_user(vertices, model.faces, 5, noise=0.0, spacing=extent / 40,
                         rng=np.random.default_rng(0))
    result = fit_points(model, user.points, user.normals, max_iter=30)
    return result.residual_mm, result.vertices


def row(path: str) -> dict:
    out: dict = {"file": Path(path).name}
    start = time.perf_counter()
    try:
        model = load_model(path)
    except DataFileError as exc:
        out["result"] = "refused: " + exc.problem
        return out
    out["load_s"] = time.perf_counter() - start
    out["result"] = "loads"
    out["vertices"], out["factors"] = model.n_vertices, model.n_factors
    out["basis |U'U-I|"] = model.info.get("statismo_basis_orthonormality", float("nan"))
    with tempfile.TemporaryDirectory() as tmp:
        save_model(Path(tmp) / "m.npz", model)
        save_model(Path(tmp) / "m.h5", load_model(Path(tmp) / "m.npz"))
        import h5py

        with h5py.File(Path(tmp) / "m.h5", "a") as h5:
            del h5["ssmstudio"]
        back = read_statismo(Path(tmp) / "m.h5")
    out["round trip mean err"] = float(np.abs(back.world_instance() - model.world_instance()).max())
    out["round trip cov gap"] = covariance_gap(model, back)
    if model.n_vertices < 100:
        out["fit"] = "too coarse to slice"
        return out
    out["mean-surface residual"], _ = fit_to(model, model.world_instance())
    coef = np.sqrt(model.coef_var) * np.random.default_rng(0).standard_normal(model.n_factors)
    truth = model.world_instance(coef)
    out["sample residual"], fitted = fit_to(model, truth)
    out["sample vertex err"] = float(np.linalg.norm(fitted - truth, axis=1).mean())
    out["extent"] = float(np.ptp(truth, axis=0).max())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path,
                        default=ROOT.parent / "shared" / "data" / "real" / "statismo")
    args = parser.parse_args()
    columns = ["file", "result", "vertices", "factors", "basis |U'U-I|", "round trip mean err",
               "round trip cov gap", "mean-surface residual", "sample residual",
               "sample vertex err", "extent", "load_s"]
    print("| " + " | ".join(columns) + " |")
    print("|" + "|".join("---" for _ in columns) + "|")
    for name in FILES:
        base = name.split("#")[0]
        if not (args.folder / base).exists():
            continue
        r = row(str(args.folder / name))
        r["file"] = name
        cells = [f"{r[c]:.3g}" if isinstance(r.get(c), float) else str(r.get(c, ""))
                 for c in columns]
        print("| " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
