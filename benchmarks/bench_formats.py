"""Benchmark of image opening: SSM Studio's readers against the libraries they wrap, side by side.

1. A 256 x 256 x 180 DICOM MR series (int16, one file a slice, oblique grid), written by
   SimpleITK/GDCM. Peers, as SimpleITK's documentation reads a series
   (``ImageSeriesReader.GetGDCMSeriesFileNames`` then ``Execute``): Execute alone, and plus
   ``GetArrayFromImage`` (a numpy array, as SSM Studio needs). SSM Studio:
   ``core.io.load_volume(folder)``: series discovery, header checks of the first file,
   reading with every slice's tags kept, the geometry checks (orientation, tilt, gaps,
   spacing, 4D), the LPS -> RAS affine and the [i, j, k] array. Target: < 2x SimpleITK.
   Then the same series beside a 20-slice localizer in one folder: choosing by UID (and by
   most files) against SimpleITK's GetGDCMSeriesIDs + GetGDCMSeriesFileNames(uid) + Execute;
   and the series beside a DICOMDIR file (pydicom's test DICOMDIR), which must not slow it.
2. The real one-file volumes of tests/data/real/dicom: the Philips enhanced file against
   SimpleITK's ReadImage (which reads the frames in file order, unchecked), the Siemens mosaic
   against nibabel's MosaicWrapper (pydicom parse + unpacking), both as arrays.
3. The same volume as NIfTI (.nii.gz), NRRD (gzip) and MetaImage (.mha, compressed):
   ``load_volume`` against ``nibabel.load(...).get_fdata``-free ``dataobj`` reading and
   ``SimpleITK.ReadImage`` + array.

Each reader runs once to warm the file cache, then ``--repeats`` times interleaved; the
median is reported. The machine is shared (2 cores for several people): times are upper
bounds, compare rows of one run.

Run: ``.venv/bin/python benchmarks/bench_formats.py [--size 256 256 180] [--repeats 5]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import formats_synth as synth  # noqa: E402

from core.io import load_volume  # noqa: E402

PHILIPS = ROOT / "tests" / "data" / "real" / "dicom" / "philips_enhanced_3d.dcm"
MOSAIC = ROOT / "tests" / "data" / "real" / "dicom" / "siemens_mosaic_1volume.IMA"


def _nibabel_mosaic(path: Path):
    import warnings

    import pydicom

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from nibabel.nicom.dicomwrappers import wrapper_from_data

        return wrapper_from_data(pydicom.dcmread(path)).get_data()


def _sitk_series(folder: Path, to_array: bool):
    import SimpleITK as sitk

    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder)))
    image = reader.Execute()
    return sitk.GetArrayFromImage(image) if to_array else image


def _sitk_two(folder: Path, uid: str):
    import SimpleITK as sitk

    assert uid in sitk.ImageSeriesReader.GetGDCMSeriesIDs(str(folder))
    reader = sitk.ImageSeriesReader()
    reader.SetFileNames(sitk.ImageSeriesReader.GetGDCMSeriesFileNames(str(folder), uid))
    return reader.Execute()


def _sitk_file(path: Path):
    import SimpleITK as sitk

    return sitk.GetArrayFromImage(sitk.ReadImage(str(path)))


def _nibabel(path: Path):
    import nibabel as nib

    return np.asanyarray(nib.load(str(path)).dataobj)


def _time(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        out.append(time.perf_counter() - start)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, nargs=3, default=(256, 256, 180))
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    import SimpleITK as sitk

    size = tuple(args.size)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        image = synth.oblique_image(size, (0.94, 0.94, 1.0), seed=0)
        start = time.perf_counter()
        synth.write_series(tmp / "series", image, description="bench")
        written = time.perf_counter() - start
        two = tmp / "two-series"  # the same series plus a 20-slice localizer
        for f in (tmp / "series").iterdir():
            two.mkdir(exist_ok=True)
            (two / f.name).symlink_to(f)
        scout = synth.oblique_image((size[0], size[1], 20), (0.94, 0.94, 5.0), seed=1)
        synth.write_series(two, scout, uid=synth.UID_ROOT + ".2", description="scout",
                           name="S{:04d}.dcm")
        uid = synth.UID_ROOT + ".1"
        with_dir = tmp / "with-dicomdir"  # the same series beside a disc's DICOMDIR index
        with_dir.mkdir()
        for f in (tmp / "series").iterdir():
            (with_dir / f.name).symlink_to(f)
        from pydicom.data import get_testdata_file

        (with_dir / "DICOMDIR").write_bytes(Path(get_testdata_file("DICOMDIR", read=False))
                                            .read_bytes())
        for name in ("v.nii.gz", "v.nrrd", "v.mha"):
            writer = sitk.ImageFileWriter()
            writer.SetFileName(str(tmp / name))
            writer.UseCompressionOn()
            writer.Execute(image)
        folder = tmp / "series"
        groups = {
            f"DICOM series {size[0]}x{size[1]}x{size[2]} ({size[2]} files)": {
                "SimpleITK ImageSeriesReader (Execute)": lambda: _sitk_series(folder, False),
                "SimpleITK ImageSeriesReader + array": lambda: _sitk_series(folder, True),
                "SSM Studio load_volume (checked)": lambda: load_volume(folder),
            },
            f"DICOM series beside a DICOMDIR ({size[2]} + 1 files)": {
                "SimpleITK ImageSeriesReader + array": lambda: _sitk_series(with_dir, True),
                "SSM Studio load_volume (DICOMDIR skipped)": lambda: load_volume(with_dir),
            },
            f"DICOM folder with 2 series ({size[2]} + 20 files)": {
                "SimpleITK GetGDCMSeriesIDs + FileNames(uid) + Execute":
                    lambda: _sitk_two(two, uid),
                "SSM Studio load_volume(series=uid)": lambda: load_volume(two, series=uid),
                "SSM Studio load_volume (most files, said)": lambda: load_volume(two,
                                                                                notify=len),
            },
            "Philips enhanced MR, one file, 96x96x40 (real)": {
                "SimpleITK ReadImage + array (GDCM: no frame checks)": lambda: _sitk_file(PHILIPS),
                "SSM Studio load_volume (pydicom, frames sorted, checked)":
                    lambda: load_volume(PHILIPS),
            },
            "Siemens mosaic, one file, 90x90x60 (real)": {
                "nibabel MosaicWrapper.get_data": lambda: _nibabel_mosaic(MOSAIC),
                "SSM Studio load_volume (pydicom + CSA, checked)": lambda: load_volume(MOSAIC),
            },
            "NIfTI .nii.gz": {
                "nibabel (dataobj array)": lambda: _nibabel(tmp / "v.nii.gz"),
                "SimpleITK ReadImage + array": lambda: _sitk_file(tmp / "v.nii.gz"),
                "SSM Studio load_volume": lambda: load_volume(tmp / "v.nii.gz"),
            },
            "NRRD (gzip)": {
                "SimpleITK ReadImage + array": lambda: _sitk_file(tmp / "v.nrrd"),
                "SSM Studio load_volume (header checked)": lambda: load_volume(tmp / "v.nrrd"),
            },
            "MetaImage .mha (compressed)": {
                "SimpleITK ReadImage + array": lambda: _sitk_file(tmp / "v.mha"),
                "SSM Studio load_volume (header checked)": lambda: load_volume(tmp / "v.mha"),
            },
        }
        # correctness first: every reader of a group gives the same voxels
        truth = sitk.GetArrayFromImage(image).T
        for path in (folder, with_dir, two, tmp / "v.nii.gz", tmp / "v.nrrd", tmp / "v.mha"):
            assert np.array_equal(load_volume(path).data, truth), path
        print(f"(series written by SimpleITK in {written:.2f} s; machine shared, times are "
              "upper bounds; median of "
              f"{args.repeats} runs after one warm-up)\n")
        for title, readers in groups.items():
            times: dict[str, list[float]] = {name: [] for name in readers}
            for fn in readers.values():
                fn()  # warm the file cache
            for _ in range(args.repeats):
                for name, fn in readers.items():
                    times[name] += _time(fn, 1)
            base = statistics.median(next(iter(times.values())))
            print(f"| {title} | median s | x first row |")
            print("|---|---:|---:|")
            for name, values in times.items():
                med = statistics.median(values)
                print(f"| {name} | {med:.3f} | {med / base:.2f} |")
            print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
