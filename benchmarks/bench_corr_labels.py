"""Benchmark: ``mesh-labels`` (a label map's structure to a mesh) against plain VTK.

On a 256^3 label map with one ellipsoid (two sizes): the CLI end to end (a fresh process:
imports, NIfTI read, Surface Nets, smoothing, remesh to 2,000 vertices, write), the same
in-process (:func:`core.correspondence.mesh_labels.label_map_surface`), and VTK's discrete
flying edges (marching cubes on the whole volume, no smoothing, no remesh) as the peer:
wall and CPU seconds (best of ``--repeats``), vertices, the volume error against the analytic
ellipsoid (%) and the mean distance of the vertices from its surface (mm).

Run: ``.venv/bin/python benchmarks/bench_corr_labels.py [--repeats 3]`` (also
``bench_correspondence.py --only labels``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from correspondence_common import ROOT

from core.io import TriMesh


def _ellipsoid_error(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray,
                     axes: np.ndarray) -> tuple[float, float]:
    """Volume error (%) against the analytic ellipsoid and mean distance (mm) of the vertices
    to its surface (first-order distance |F - 1| / |grad F|, F = sum((x - c)^2 / a^2)^(1/2))."""
    from core.geometry import mesh as meshops

    q = (vertices - centre) / axes
    r = np.linalg.norm(q, axis=1)
    grad = np.linalg.norm(q / axes / np.maximum(r[:, None], 1e-12), axis=1)
    volume = 4.0 / 3.0 * np.pi * np.prod(axes)
    return (100.0 * (meshops.volume(vertices, faces) / volume - 1.0),
            float(np.mean(np.abs(r - 1.0) / grad)))


def labels_table(repeats: int = 3) -> None:
    """``mesh-labels`` on a 256^3 label map with one structure: the CLI end to end (a fresh
    process: imports, NIfTI read, Surface Nets, smoothing, remesh to 2,000 vertices, write),
    the same in-process, and plain VTK discrete flying edges (marching cubes on the whole
    volume, no smoothing, no remesh) as the peer."""
    import resource
    import subprocess
    import tempfile

    import nibabel as nib
    import vtk
    from vtk.util.numpy_support import numpy_to_vtk

    from core.correspondence.mesh_labels import label_map_surface, polydata_arrays
    from core.io import load_volume

    print("\nmesh-labels, 256^3 uint8 label map (1 mm voxels), one structure, --vertices 2000; "
          "best of %d; shared machine: times are upper bounds" % repeats)
    print("(wall s is inflated by the other users' load; cpu s = user + system CPU of the "
          "process, all threads)")
    print(f"{'structure':<30}{'method':<34}{'wall s':>7}{'cpu s':>7}{'vertices':>10}"
          f"{'volume %':>10}{'dist mm':>9}")
    n = 256
    i, j, k = np.ogrid[:n, :n, :n]
    for label, axes in (("ellipsoid 120 x 80 x 60 mm", (60.0, 40.0, 30.0)),
                        ("ellipsoid 24 x 16 x 12 mm", (12.0, 8.0, 6.0))):
        axes = np.array(axes)
        centre = np.array([128.3, 120.6, 130.2])
        data = ((((i - centre[0]) / axes[0]) ** 2 + ((j - centre[1]) / axes[1]) ** 2
                 + ((k - centre[2]) / axes[2]) ** 2) <= 1.0).astype(np.uint8) * 17
        with tempfile.TemporaryDirectory() as tmp:
            path = f"{tmp}/labels.nii.gz"
            nib.save(nib.Nifti1Image(data, np.eye(4)), path)
            rows = []
            best, best_cpu = np.inf, np.inf
            for _ in range(repeats):
                t0 = time.perf_counter()
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                subprocess.run([sys.executable, "-m", "core.cli", "mesh-labels", path, "--label", "17",
                                "--out", f"{tmp}/out"], check=True, cwd=ROOT, capture_output=True)
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                best = min(best, time.perf_counter() - t0)
                best_cpu = min(best_cpu, after.ru_utime - before.ru_utime
                               + after.ru_stime - before.ru_stime)
            from core.io import load_mesh

            mesh = load_mesh(f"{tmp}/out/labels_label_17.vtk") if Path(
                f"{tmp}/out/labels_label_17.vtk").exists() else load_mesh(
                next(Path(f"{tmp}/out").glob("*.vtk")))
            rows.append(("ssm-studio CLI (fresh process)", best, best_cpu, mesh))
            times, cpus = [], []
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                mesh = label_map_surface(path, 17)
                times.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            rows.append(("ssm-studio in-process", min(times), min(cpus), mesh))
            volume = load_volume(path)
            times, cpus = [], []
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                mask = (np.asarray(volume.data) == 17).astype(np.uint8)
                image = vtk.vtkImageData()
                image.SetDimensions(*mask.shape)
                image.GetPointData().SetScalars(numpy_to_vtk(mask.ravel(order="F"), deep=True))
                fe = vtk.vtkDiscreteFlyingEdges3D()
                fe.SetInputData(image)
                fe.SetValue(0, 1)
                fe.Update()
                v, f = polydata_arrays(fe.GetOutput())
                times.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0)
            rows.append(("VTK discrete flying edges", min(times), min(cpus), TriMesh(v, f)))
        for method, seconds, cpu, m in rows:
            vol_err, dist = _ellipsoid_error(m.vertices, m.faces, centre, axes)
            print(f"{label:<30}{method:<34}{seconds:>7.2f}{cpu:>7.2f}{m.n_vertices:>10}"
                  f"{vol_err:>10.2f}{dist:>9.3f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="runs per method, best kept (3)")
    args = parser.parse_args(argv)
    labels_table(args.repeats)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
