"""ICP's plane weight and pose prior, refitted on the models ``bench_end_to_end.py --cache``
kept (issue 27 item 5; RESULTS "ICP's pose prior and plane weight").

Today's ICP (:class:`core.reconstruction.covariance.NearestPoint`) is point-to-plane with a
normal / tangential weight :data:`~core.reconstruction.covariance.PLANE_WEIGHT` and the fit's
pose prior (``fit_points(pose_spread=1)``). For every cached model of today's pipeline in the
folder, each held-out shape's contours (3 orthogonal, 2 parallel; the same simulated user as
``bench_end_to_end.py``) are fitted with ICP under each variant, placed at the points; the
symmetric surface distance to the true surface (mm), per family and layout, with the paired
difference against today's settings (mean +- standard error over the held-out shapes).

    PYTHONPATH=. python benchmarks/diag_icp_prior.py CACHE [--plane W ...] [--spread S ...]
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_end_to_end import held_out_cases, surface_error  # noqa: E402

import core.reconstruction.covariance as covariance  # noqa: E402
from core.models.shape_model import ShapeModel  # noqa: E402
from core.reconstruction import fit_points  # noqa: E402

CACHED = re.compile(r"(.+)_seed(\d+)_n(\d+)_h(\d+)_today")


def refit(cache: Path, variants: list[tuple[float, float]]) -> dict:
    """variant -> layout -> family -> [error per held-out shape]."""
    today = covariance.PLANE_WEIGHT
    out: dict = {}
    for path in sorted(cache.glob("*_today*.npz")):
        family, seed, _, held_out = CACHED.match(path.name).groups()
        data = dict(np.load(path))
        if "error" in data:
            continue
        model = ShapeModel(mean=data["mean"], factors=data["factors"], coef_var=data["coef_var"],
                           faces=data["faces"], world_transform=data["world"], method="pca")
        for case in held_out_cases(family, int(held_out), int(seed)):
            for plane, spread in variants:
                covariance.PLANE_WEIGHT = plane
                try:
                    fit = fit_points(model, case["points"], case["normals"], method="icp",
                                     placement="points", pose_spread=spread)
                finally:
                    covariance.PLANE_WEIGHT = today
                out.setdefault((plane, spread), {}).setdefault(case["layout"], {}).setdefault(
                    family, []).append(surface_error(fit.vertices, model.faces, case["mesh"]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cache", type=Path, help="bench_end_to_end.py --cache folder")
    ap.add_argument("--plane", type=float, nargs="+", default=[covariance.PLANE_WEIGHT, 300.0])
    ap.add_argument("--spread", type=float, nargs="+", default=[1.0, 8.0])
    args = ap.parse_args()
    variants = [(p, s) for p in args.plane for s in args.spread]
    out = refit(args.cache, variants)
    base = out[variants[0]]
    print("icp: symmetric surface distance (mm); in brackets, minus plane "
          f"{variants[0][0]:g} spread {variants[0][1]:g}, paired by held-out shape")
    for (plane, spread), cells in out.items():
        for layout, families in cells.items():
            text = []
            for family, errors in families.items():
                d = np.asarray(errors) - np.asarray(base[layout][family])
                se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else 0.0
                text.append(f"{family} {np.mean(errors):.3f} ({d.mean():+.3f} +- {se:.3f}, n {len(d)})")
            print(f"plane {plane:6g} spread {spread:4g}  {layout:13s} " + " | ".join(text))


if __name__ == "__main__":
    main()
