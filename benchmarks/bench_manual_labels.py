"""Manual-looking label maps -> surfaces -> model: topology before/after and accuracy (issue 28).

Tables:

- ``labels``: per grid (0.3 mm, 1 mm, 0.5 x 0.5 x 2 mm) and solid, over seeds: the Surface
  Nets surface of the raw mask, welded (what ``mesh-labels`` meshed until 2026-12-02), vs
  ``mesh-labels`` now: open edges, non-manifold edges/vertices, pieces, genus, islands
  dropped (count, voxels), mean distance to the true surface (mm) and seconds.
- ``grooming``: marching cubes + Taubin + quadric decimation meshes of the same raw masks
  (what other tools give), before grooming and after: the same counts and the distance.
- ``fit``: 6 subjects -> ``mesh-labels`` -> ``correspond`` -> ``build-model`` -> ``fit`` to a
  held-out 7th subject's surface; distance of the fit to that subject's true surface.

``python benchmarks/bench_manual_labels.py [--only labels|grooming|fit] [--seeds 3]``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.correspondence import grooming  # noqa: E402
from core.correspondence.mesh_labels import label_surface, mask_surface  # noqa: E402
from core.datasets.label_maps import manual_label_map, marching_cubes_mesh, population  # noqa: E402
from core.geometry import mesh as meshops

GRIDS = {"0.3 mm": (0.3, 0.3, 0.3), "1 mm": (1.0, 1.0, 1.0), "0.5x0.5x2 mm": (0.5, 0.5, 2.0)}
if "--grids" in sys.argv:  # e.g. --grids 0.5x0.5x2
    wanted = sys.argv.pop(sys.argv.index("--grids") + 1).split(",")
    sys.argv.remove("--grids")
    GRIDS = {k: v for k, v in GRIDS.items() if any(k.startswith(w) for w in wanted)}
KINDS = ("pallidum", "bean", "ring")


def _counts(v, f) -> str:
    t = meshops.topology(f, len(v))
    return (f"{t['open_edges']:5d} {t['non_manifold_edges']:5d} {t['non_manifold_vertices']:5d} "
            f"{t['pieces']:4d} {str(t['genus']):>5}")


def _cases(kinds, seeds: int, title: str, columns: str):
    """Print the table's title and header; yield (row label, label map) per case."""
    print(title)
    print(f"{'grid':13} {'solid':9} seed {'':5}{'open':>5} {'nm-e':>5} {'nm-v':>5} {'pcs':>4} "
          f"{'genus':>5}  {columns}")
    for grid, spacing in GRIDS.items():
        for kind in kinds:
            for seed in range(seeds):
                yield f"{grid:13} {kind:9} {seed:4d}", manual_label_map(kind, spacing, seed=seed)


def table_labels(seeds: int) -> None:
    for row, lm in _cases(KINDS, seeds, "labels: before = Surface Nets of the raw mask, welded; "
                          "after = mesh-labels --vertices 0", "islands(vox)  dist mm   s"):
        v, f = mask_surface(lm.volume.data == 1, lm.volume.affine)
        v, f, _, _ = grooming.weld(v, f)
        print(f"{row} before{_counts(v, f)}  {'':12}  {lm.distance(v).mean():6.3f}")
        start = time.perf_counter()
        info: dict = {}
        mesh = label_surface(lm.volume, 1, n_vertices=None, info=info)
        sec = time.perf_counter() - start
        print(f"{'':28} after {_counts(mesh.vertices, mesh.faces)}  {info['islands']:4d} "
              f"({info['island_voxels']:4d})  {lm.distance(mesh.vertices).mean():6.3f} {sec:5.1f}"
              f"  truth genus {lm.genus}")


def table_grooming(seeds: int) -> None:
    for row, lm in _cases(("pallidum", "bean"), seeds, "grooming: marching cubes + quadric "
                          "decimation (3000 triangles) -> groom_mesh (1000 vertices)",
                          "dist mm  what grooming did"):
        mesh = marching_cubes_mesh(lm, 3000)
        print(f"{row} before{_counts(mesh.vertices, mesh.faces)}  "
              f"{lm.distance(mesh.vertices).mean():6.3f}")
        try:
            out, rep = grooming.groom_mesh(mesh, {"vertices": 1000})
        except grooming.GroomingError as exc:
            print(f"{'':28} refused: {exc}")
            continue
        print(f"{'':28} after {_counts(out.vertices, out.faces)}  "
              f"{lm.distance(out.vertices).mean():6.3f}  {grooming.describe(rep.to_dict())}")


def table_fit(seeds: int) -> None:
    from core.cli import main
    from core.io import load_mesh, save_volume

    print("fit: 6 pallidum label maps (1 mm; 2 of them 0.5x0.5x2 mm) -> model -> fit to a 7th")
    spacings = [(1.0, 1.0, 1.0)] * 4 + [(0.5, 0.5, 2.0)] * 2 + [(1.0, 1.0, 1.0)]
    for seed in range(seeds):
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            subjects = [population("pallidum", 1, sp, seed=100 * seed + 20 + i)[0]
                        for i, sp in enumerate(spacings)]
            maps = []
            for i, s in enumerate(subjects):
                maps.append(str(d / f"s{i}.nii.gz"))
                save_volume(maps[-1], s.volume.data, s.volume.affine)
            start = time.perf_counter()
            main(["mesh-labels", *maps, "--label", "1", "--vertices", "600", "--out", str(d / "raw")])
            outs = [e["output"] for e in json.loads((d / "raw" / "mesh_labels.json").read_text())["inputs"]]
            main(["correspond", *outs[:6], "--out", str(d / "corr"), "--vertices", "600",
                  "--refine", "1", "--jobs", "1"])
            main(["build-model", str(d / "corr"), "--out", str(d / "model.npz")])
            held = load_mesh(outs[6])
            np.savetxt(d / "p.csv", held.vertices, delimiter=",", header="x,y,z", comments="")
            centre = ",".join(f"{c:.3f}" for c in held.vertices.mean(axis=0))
            main(["fit", "--model", str(d / "model.npz"), "--points", str(d / "p.csv"),
                  f"--placement={centre}", "--pose-spread", "5", "--out", str(d / "fit.vtk")])
            fit = load_mesh(d / "fit.vtk")
            dist = subjects[6].distance(fit.vertices)
            raw = subjects[6].distance(held.vertices)
            print(f"seed {seed}: fit -> true surface mean {dist.mean():.3f} mm, 95% "
                  f"{np.percentile(dist, 95):.3f}, max {dist.max():.3f}; the held-out subject's "
                  f"own mesh-labels surface: mean {raw.mean():.3f} mm; "
                  f"{time.perf_counter() - start:.0f} s in all", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=("labels", "grooming", "fit"))
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    for name, fn in (("labels", table_labels), ("grooming", table_grooming), ("fit", table_fit)):
        if args.only in (None, name):
            fn(args.seeds)
            print(flush=True)


if __name__ == "__main__":
    main()
