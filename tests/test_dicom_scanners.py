"""DICOM as today's scanners write it: enhanced multi-frame files, Siemens mosaics, DICOMDIR
discs, gantry tilt, several series in a folder, and impossible tags.

Real files (tests/data/real/dicom/SOURCES.md, and the Siemens 2-D series in
../shared/data/real/dicom/) are checked against geometry computed here, independently of the
reader, from their own tags as dcm2niix places them: the world (LPS) position of voxel
(i, j, k) is ImagePositionPatient of the k-th slice along the normal + i * column spacing *
row direction + j * row spacing * column direction; SSM Studio's RAS is LPS with x, y negated.
Synthetic enhanced files are written with pydicom to resemble the real Philips one.
"""

from __future__ import annotations

import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

pydicom = pytest.importorskip("pydicom")
import formats_synth as synth  # noqa: E402
from pydicom.data import get_testdata_file  # noqa: E402
from pydicom.dataset import Dataset, FileMetaDataset  # noqa: E402
from pydicom.sequence import Sequence  # noqa: E402

from core.io import DataFileError, load_volume  # noqa: E402
from core.io import dicom as dicom_io  # noqa: E402

HERE = Path(__file__).resolve().parent
REAL = HERE / "data" / "real" / "dicom"
PHILIPS = REAL / "philips_enhanced_3d.dcm"
MOSAIC = REAL / "siemens_mosaic_1volume.IMA"
# ../shared beside the clone (as CI lays it out), or one level further up from a worktree
SHARED = next((p for p in (HERE.parents[1] / "shared", HERE.parents[2] / "shared")
               if p.is_dir()), HERE.parents[1] / "shared") / "data" / "real" / "dicom"
SIEMENS_2D = SHARED / "siemens_flash2d_35slices"
SIEMENS_4 = REAL / "siemens_flash2d_4slices"   # its first 4 slices, kept with the tests
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])
ENHANCED_MR = "1.2.840.10008.5.1.4.1.1.4.1"


def _read(path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return pydicom.dcmread(path)


def _ras(volume, ijk) -> np.ndarray:
    return (volume.affine @ np.append(np.asarray(ijk, dtype=float), 1.0))[:3]


def _corners(shape):
    return [(i, j, k) for i in (0, shape[0] - 1) for j in (0, shape[1] - 1)
            for k in (0, shape[2] - 1)]


# -- real files -------------------------------------------------------------------------------

def test_siemens_2d_series_matches_its_slice_tags():
    """35 sagittal slices (patient decubitus left): each voxel where its own file puts it."""
    if not SIEMENS_2D.is_dir():
        pytest.skip(f"the whole series is not here ({SIEMENS_2D.name}: ../shared beside the clone)")
    files = sorted(SIEMENS_2D.iterdir())
    slices = [_read(f) for f in files]
    row, col = (np.array(slices[0].ImageOrientationPatient[:3], float),
                np.array(slices[0].ImageOrientationPatient[3:], float))
    normal = np.cross(row, col)
    slices.sort(key=lambda ds: float(np.array(ds.ImagePositionPatient, float) @ normal))
    dy, dx = (float(v) for v in slices[0].PixelSpacing)
    vol = load_volume(SIEMENS_2D)
    assert vol.shape == (256, 256, 35)
    steps = np.diff([np.array(ds.ImagePositionPatient, float) @ normal for ds in slices])
    assert np.allclose(vol.spacing, (dx, dy, steps.mean()), atol=1e-4)
    assert np.allclose(vol.spacing, (1.015625, 1.015625, 4.8), atol=1e-4)
    for i, j, k in _corners(vol.shape) + [(100, 37, 17)]:
        lps = np.array(slices[k].ImagePositionPatient, float) + i * dx * row + j * dy * col
        assert np.allclose(_ras(vol, (i, j, k)), LPS_TO_RAS @ lps, atol=1e-3)
    for k in (0, 17, 34):
        assert np.array_equal(vol.data[:, :, k], slices[k].pixel_array.T)


def test_philips_enhanced_file_is_one_3d_volume_placed_frame_by_frame():
    ds = _read(PHILIPS)
    frames = ds.PerFrameFunctionalGroupsSequence
    assert int(ds.NumberOfFrames) == 40 and len(frames) == 40
    assert {f.FrameContentSequence[0].TemporalPositionIndex for f in frames} == {1}
    pos = np.array([f.PlanePositionSequence[0].ImagePositionPatient for f in frames], float)
    ori = np.array(frames[0].PlaneOrientationSequence[0].ImageOrientationPatient, float)
    row, col = ori[:3], ori[3:]
    normal = np.cross(row, col)
    order = np.argsort(pos @ normal)
    assert len(np.unique(np.round(pos, 2), axis=0)) == 40  # 40 positions: one volume
    dy, dx = (float(v) for v in frames[0].PixelMeasuresSequence[0].PixelSpacing)
    slope = np.array([float(f.PixelValueTransformationSequence[0].RescaleSlope) for f in frames])
    intercept = np.array([float(f.PixelValueTransformationSequence[0].RescaleIntercept)
                          for f in frames])
    vol = load_volume(PHILIPS)
    assert vol.shape == (96, 96, 40)
    assert np.allclose(vol.spacing, (2.5, 2.5, 4.0), atol=1e-5)
    for i, j, k in _corners(vol.shape) + [(50, 13, 21)]:
        lps = pos[order[k]] + i * dx * row + j * dy * col
        assert np.allclose(_ras(vol, (i, j, k)), LPS_TO_RAS @ lps, atol=1e-4)
    stored = ds.pixel_array
    for k in (0, 20, 39):
        f = order[k]
        assert np.allclose(vol.data[:, :, k], stored[f].T * slope[f] + intercept[f], atol=1e-4)
    assert np.isclose(float(vol.data.max()), 4031 * 0.1, atol=1e-3)  # RescaleSlope 0.1 applied


def _phoenix_slice_centres(ds) -> np.ndarray:
    """Slice centres (LPS) the scanner's protocol (MrPhoenixProtocol in the CSA series
    header) prescribed: sSliceArray.asSlice[n].sPosition.dSag/dCor/dTra, 0 when absent."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from nibabel.nicom import csareader
    text = csareader.get_csa_header(ds, "series")["tags"]["MrPhoenixProtocol"]["items"][0]
    n = int(re.search(r"sSliceArray\.lSize\s*=\s*(\d+)", text).group(1))
    centres = np.zeros((n, 3))
    for m in re.finditer(r"sSliceArray\.asSlice\[(\d+)\]\.sPosition\.d(Sag|Cor|Tra)\s*=\s*"
                         r"(\S+)", text):
        centres[int(m.group(1)), "SagCorTra".index(m.group(2)) // 3] = float(m.group(3))
    return centres


def test_siemens_mosaic_unpacked_at_the_slices_the_protocol_prescribed():
    """The 60 tiles of the mosaic are 60 slices; each slice's centre (voxel (c/2, r/2): the
    field of view's centre of an even matrix) is where the protocol put it."""
    ds = _read(MOSAIC)
    centres = _phoenix_slice_centres(ds)
    vol = load_volume(MOSAIC)
    assert vol.shape == (90, 90, 60) and centres.shape == (60, 3)
    assert np.allclose(vol.spacing, 2.4, atol=1e-6)
    for k in range(60):
        assert np.allclose(_ras(vol, (45, 45, k)), LPS_TO_RAS @ centres[k], atol=1e-3), k
    mosaic = ds.pixel_array
    tile = 720 // 8
    for k in (0, 9, 59):  # tile k: row k // 8, column k % 8 of the 8 x 8 grid
        r, c = divmod(k, 8)
        assert np.array_equal(vol.data[:, :, k],
                              mosaic[r * tile:(r + 1) * tile, c * tile:(c + 1) * tile].T)
    # nibabel's MosaicWrapper (an independent implementation) agrees on every voxel
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from nibabel.nicom.dicomwrappers import wrapper_from_data
        wrapper = wrapper_from_data(ds)
        assert np.array_equal(wrapper.get_data().transpose(1, 0, 2), vol.data)
    swap = np.eye(4)[[1, 0, 2, 3]]  # nibabel indexes (row, column, slice)
    assert np.allclose(np.diag([-1, -1, 1, 1]) @ wrapper.affine @ swap, vol.affine, atol=1e-4)


def test_mosaic_slice_order_follows_the_csa_normal_not_the_cross_product(tmp_path):
    """Column direction reversed in ImageOrientationPatient: row x column now points down but
    the CSA SliceNormalVector still up, so the slices still go up, as the protocol says."""
    ds = _read(MOSAIC)
    centres = _phoenix_slice_centres(ds)
    ds.ImageOrientationPatient = [1, 0, 0, 0, -1, 0]
    ds.save_as(tmp_path / "flipped.IMA")
    vol = load_volume(tmp_path / "flipped.IMA")
    z = np.array([_ras(vol, (45, 45, k))[2] for k in range(60)])
    assert np.allclose(z, centres[:, 2], atol=1e-3)


def test_mosaic_series_of_several_volumes_is_refused_as_4d(tmp_path):
    for t in range(3):
        ds = _read(MOSAIC)
        ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = f"{synth.UID_ROOT}.7.{t}"
        ds.InstanceNumber = t + 1
        ds.AcquisitionNumber = t + 1
        ds.save_as(tmp_path / f"vol{t}.IMA")
    with pytest.raises(DataFileError, match="4D mosaic series: 3 Siemens mosaic files"):
        load_volume(tmp_path)


# -- synthetic enhanced files, made to resemble the Philips one -------------------------------

def _item(**values) -> Dataset:
    item = Dataset()
    for key, value in values.items():
        setattr(item, key, value)
    return item


def write_enhanced(path: Path, *, slices=6, volumes=1, stacks=1, rows=7, cols=9,
                   spacing=(0.8, 1.1), gap=2.5, angle=23.0, origin=(-80.0, 95.0, -30.0),
                   shuffle=True, shared=False, slopes=None, seed=0) -> dict:
    """An Enhanced MR Image file (pydicom) of ``volumes`` x ``slices`` frames on an oblique
    grid, frames stored out of slice order; returns the truth the reader must find."""
    rng = np.random.default_rng(seed)
    rot = synth.rotation((0.2, 0.6, 0.7), angle)
    row, col, normal = rot[:, 0], rot[:, 1], rot[:, 2]
    n = slices * volumes * stacks
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ENHANCED_MR
    meta.MediaStorageSOPInstanceUID = f"{synth.UID_ROOT}.8.1"
    meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID, ds.SOPInstanceUID = ENHANCED_MR, meta.MediaStorageSOPInstanceUID
    ds.SeriesInstanceUID, ds.StudyInstanceUID = f"{synth.UID_ROOT}.8", f"{synth.UID_ROOT}.100"
    ds.Modality, ds.Manufacturer, ds.SeriesDescription = "MR", "Philips", "3D test"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "M", "NONE"]
    ds.Rows, ds.Columns, ds.NumberOfFrames = rows, cols, n
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    orientation = [float(v) for v in np.concatenate([row, col])]
    measures = _item(PixelSpacing=list(spacing), SliceThickness=gap, SpacingBetweenSlices=gap)
    frame_list = [(v, s, k) for v in range(volumes) for s in range(stacks) for k in range(slices)]
    order = rng.permutation(n) if shuffle else np.arange(n)
    slopes = np.asarray(slopes if slopes is not None else rng.uniform(0.5, 2.0, n), float)
    stored = rng.integers(0, 4096, size=(n, rows, cols)).astype(np.uint16)
    per_frame = Sequence()
    for f in range(n):
        v, s, k = frame_list[order[f]]
        position = np.asarray(origin) + (k + s * (slices + 3)) * gap * normal
        item = _item(
            FrameContentSequence=Sequence([_item(TemporalPositionIndex=v + 1, StackID=str(s + 1),
                                                 InStackPositionNumber=k + 1,
                                                 DimensionIndexValues=[s + 1, k + 1])]),
            PlanePositionSequence=Sequence([_item(ImagePositionPatient=[float(x)
                                                                        for x in position])]),
            PixelValueTransformationSequence=Sequence([_item(
                RescaleSlope=f"{slopes[f]:.6f}", RescaleIntercept="-3.5", RescaleType="US")]))
        if not shared:
            item.PlaneOrientationSequence = Sequence([_item(ImageOrientationPatient=orientation)])
            item.PixelMeasuresSequence = Sequence([measures])
        per_frame.append(item)
    ds.PerFrameFunctionalGroupsSequence = per_frame
    shared_item = Dataset()
    if shared:
        shared_item.PlaneOrientationSequence = Sequence([_item(
            ImageOrientationPatient=orientation)])
        shared_item.PixelMeasuresSequence = Sequence([measures])
    ds.SharedFunctionalGroupsSequence = Sequence([shared_item])
    ds.PixelData = stored.tobytes()
    ds.save_as(path, enforce_file_format=True)
    slopes = np.array([float(f"{s:.6f}") for s in slopes])
    return {"row": row, "col": col, "normal": normal, "origin": np.asarray(origin),
            "order": order, "stored": stored, "slopes": slopes, "frames": frame_list}


@pytest.mark.parametrize("shared", [False, True], ids=["per-frame groups", "shared groups"])
def test_synthetic_enhanced_volume_is_read_exactly(tmp_path, shared):
    truth = write_enhanced(tmp_path / "enh.dcm", shared=shared)
    vol = load_volume(tmp_path / "enh.dcm")
    dy, dx, gap = 0.8, 1.1, 2.5
    assert vol.shape == (9, 7, 6)
    assert np.allclose(vol.spacing, (dx, dy, gap), atol=1e-9)
    for i, j, k in _corners(vol.shape) + [(4, 3, 2)]:
        lps = truth["origin"] + i * dx * truth["row"] + j * dy * truth["col"] \
            + k * gap * truth["normal"]
        assert np.allclose(_ras(vol, (i, j, k)), LPS_TO_RAS @ lps, atol=1e-6)
    for k in range(6):  # slice k is the stored frame that holds slice k, scaled by its slope
        f = int(np.flatnonzero(truth["order"] == k)[0])
        expected = truth["stored"][f].T * truth["slopes"][f] - 3.5
        assert np.allclose(vol.data[:, :, k], expected, atol=1e-3)


@pytest.mark.parametrize("kw, words", [
    ({"volumes": 2}, ["4D data, 2 volumes", "12 frames at 6 slice positions",
                      "2 temporal positions"]),
    ({"volumes": 3, "slices": 4}, ["3 volumes", "12 frames at 4 slice positions"]),
    ({"stacks": 2}, ["2 volumes", "2 stacks"]),
], ids=["2 time points", "3 time points", "2 stacks"])
def test_synthetic_4d_enhanced_file_is_refused_saying_how_many_volumes(tmp_path, kw, words):
    write_enhanced(tmp_path / "enh4d.dcm", **kw)
    with pytest.raises(DataFileError) as err:
        load_volume(tmp_path / "enh4d.dcm")
    text = str(err.value)
    assert "\n" not in text and "enh4d.dcm" in text
    for word in words:
        assert word in text, text


def test_real_philips_frames_repeated_as_two_time_points_are_refused(tmp_path):
    import copy

    ds = _read(PHILIPS)
    again = copy.deepcopy(ds.PerFrameFunctionalGroupsSequence)
    for f in again:
        f.FrameContentSequence[0].TemporalPositionIndex = 2
    ds.PerFrameFunctionalGroupsSequence = Sequence(list(ds.PerFrameFunctionalGroupsSequence)
                                                   + list(again))
    ds.NumberOfFrames = 80
    ds.PixelData = ds.PixelData * 2
    ds.save_as(tmp_path / "philips4d.dcm")
    with pytest.raises(DataFileError, match=r"2 volumes: 80 frames at 40 slice positions "
                                            r"\(2 temporal positions\)"):
        load_volume(tmp_path / "philips4d.dcm")


def test_enhanced_file_with_a_gap_between_frames_is_refused(tmp_path):
    """A frame missing from the middle of the stack: a gap, named like a series' gap."""
    truth = write_enhanced(tmp_path / "enh.dcm", shuffle=False)
    ds = _read(tmp_path / "enh.dcm")
    keep = [f for f in range(6) if truth["frames"][f][2] != 3]
    ds.PerFrameFunctionalGroupsSequence = Sequence(
        [ds.PerFrameFunctionalGroupsSequence[f] for f in keep])
    ds.NumberOfFrames = len(keep)
    ds.PixelData = truth["stored"][keep].tobytes()
    ds.save_as(tmp_path / "gap.dcm")
    with pytest.raises(DataFileError, match="1 slice.s. missing: a gap of 5 mm after frame 3"):
        load_volume(tmp_path / "gap.dcm")


# -- DICOMDIR, gantry tilt ---------------------------------------------------------------------

DICOMDIR = Path(get_testdata_file("DICOMDIR", read=False))


def _ct_series(folder: Path, n: int = 5, tilt: float = 0.0, uid: str = ".5",
               dicomdir: str | None = "DICOMDIR") -> list:
    """Slices of pydicom's real CT_small.dcm (128 x 128, 0.66 mm), 5 mm apart; a gantry tilt
    shifts each slice along y by 5 mm * tan(tilt) and says so in GantryDetectorTilt."""
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for k in range(n):
        ds = _read(get_testdata_file("CT_small.dcm"))
        ds.SeriesInstanceUID = synth.UID_ROOT + uid
        ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = \
            f"{synth.UID_ROOT}{uid}.{k + 1}"
        ds.InstanceNumber = k + 1
        x, y, z = (float(v) for v in ds.ImagePositionPatient)
        ds.ImagePositionPatient = [x, y + 5.0 * k * np.tan(np.radians(tilt)), z + 5.0 * k]
        ds.GantryDetectorTilt = tilt
        ds.save_as(folder / f"CT{k:03d}.dcm")
        written.append(ds)
    if dicomdir:
        shutil.copy(DICOMDIR, folder / dicomdir)
    return written


@pytest.mark.parametrize("name", ["DICOMDIR", "DIRFILE"])
def test_dicomdir_beside_a_series_is_skipped_quietly_and_cheaply(tmp_path, name):
    written = _ct_series(tmp_path / "ct", dicomdir=name)
    assert dicom_io.is_dicomdir(tmp_path / "ct" / name)  # by name or by SOP class
    # the one-scan path is still taken: the DICOMDIR does not make it list every series
    assert dicom_io._single_series(tmp_path / "ct") is not None
    vol = load_volume(tmp_path / "ct")
    assert vol.shape == (128, 128, 5) and np.allclose(vol.spacing, (0.661468, 0.661468, 5.0))
    assert np.allclose(vol.data[:, :, 2], written[2].pixel_array.T * 1.0 - 1024)


@pytest.mark.parametrize("name", ["DICOMDIR", "DIRFILE"])
def test_tilted_ct_beside_a_dicomdir_is_refused_for_its_tilt(tmp_path, name):
    _ct_series(tmp_path / "ct", tilt=15.0, dicomdir=name)
    with pytest.raises(DataFileError) as err:
        load_volume(tmp_path / "ct")
    text = str(err.value)
    assert "gantry tilt of 15 degrees (GantryDetectorTilt)" in text and "15.00 degrees" in text
    assert name not in text and "corrupt" not in text and "\n" not in text


def test_folder_with_only_a_dicomdir_says_so(tmp_path):
    (tmp_path / "disc").mkdir()
    shutil.copy(DICOMDIR, tmp_path / "disc" / "DICOMDIR")
    with pytest.raises(DataFileError, match="only a DICOMDIR"):
        load_volume(tmp_path / "disc")


# -- several series in a folder -----------------------------------------------------------------

def test_unreadable_default_series_names_the_readable_others_and_series_option(tmp_path):
    folder = tmp_path / "study"
    _ct_series(folder, n=6, tilt=12.0, uid=".51", dicomdir=None)  # most files, unreadable
    small = synth.oblique_image((6, 5, 4), (1.0, 1.0, 3.0), seed=1)
    synth.write_series(folder, small, uid=synth.UID_ROOT + ".52", description="T1 small",
                       name="S{:04d}.dcm")
    notes = []
    with pytest.raises(DataFileError) as err:
        load_volume(folder, notify=notes.append)
    text = str(err.value)
    assert "\n" not in text
    assert f"series {synth.UID_ROOT}.51" in text and "taken as the one with most files" in text
    assert "gantry tilt" in text
    assert f"other readable series: {synth.UID_ROOT}.52" in text and "--series UID" in text
    assert len(notes) == 1 and "--series UID" in notes[0] and synth.UID_ROOT + ".52" in notes[0]
    assert load_volume(folder, series=synth.UID_ROOT + ".52").shape == (6, 5, 4)


def test_gui_choice_without_dialog_names_the_others(tmp_path):
    from app import formats

    folder = tmp_path / "study"
    _ct_series(folder, n=6, uid=".61", dicomdir="DICOMDIR")
    synth.write_series(folder, synth.oblique_image((6, 5, 4), (1.0, 1.0, 3.0)),
                       uid=synth.UID_ROOT + ".62", description="T1 small", name="S{:04d}.dcm")
    notes = []
    chosen = formats.resolve_dicom_choice(folder, None, notes.append)
    assert chosen.name.startswith("CT")
    assert len(notes) == 1 and "2 series" in notes[0] and synth.UID_ROOT + ".61" in notes[0]
    assert f"others: {synth.UID_ROOT}.62" in notes[0] and "--series UID" in notes[0]


# -- impossible tags: each a one-line refusal naming the file and the tag ------------------------

def _siemens_slices(tmp: Path, change, which=None) -> Path:
    """The first 4 slices (along the normal) of the real Siemens series, ``change(ds)`` applied
    to every one (or to slice ``which``)."""
    files = sorted(SIEMENS_4.iterdir())
    slices = [(f, _read(f)) for f in files]
    row = np.array(slices[0][1].ImageOrientationPatient[:3], float)
    col = np.array(slices[0][1].ImageOrientationPatient[3:], float)
    slices.sort(key=lambda p: float(np.array(p[1].ImagePositionPatient, float)
                                    @ np.cross(row, col)))
    out = tmp / "series"
    out.mkdir()
    for k, (f, ds) in enumerate(slices[:4]):
        if which is None or k == which:
            change(ds)
        ds.save_as(out / f"slice{k}.dcm")
    return out


def _one(tmp: Path, source: Path, change) -> Path:
    ds = _read(source)
    change(ds)
    out = tmp / ("bad" + source.suffix)
    ds.save_as(out)
    return out


def _set(keyword, value):
    def change(ds):
        setattr(ds, keyword, value)
    return change


def _set_raw(tag, vr, text: str):
    """Write a text value as given (pydicom would refuse 'nan' through its DS type)."""
    def change(ds):
        ds[tag] = pydicom.DataElement(tag, vr, text)
    return change


def _frame(n, sequence, tag, vr, text):
    def change(ds):
        item = ds.PerFrameFunctionalGroupsSequence[n][sequence][0]
        item[tag] = pydicom.DataElement(tag, vr, text)
    return change


def _half_pixels(ds):
    ds.PixelData = ds.PixelData[:len(ds.PixelData) // 2]


def _series(change, which=None):
    return lambda tmp: _siemens_slices(tmp, change, which)


def _file(source, change):
    return lambda tmp: _one(tmp, source, change)


BAD_TAGS = {
    "series PixelSpacing NaN": (_series(_set_raw(0x00280030, "DS", "nan\\nan")),
                                "slice0.dcm: PixelSpacing (0028,0030) is 'nan\\nan'"),
    "series PixelSpacing 0": (_series(_set_raw(0x00280030, "DS", "0\\0")),
                              "PixelSpacing (0028,0030) is '0\\0'"),
    "series PixelSpacing negative": (
        _series(_set_raw(0x00280030, "DS", "-1.015625\\1.015625")),
        "PixelSpacing (0028,0030) is '-1.015625\\1.015625'"),
    "series PixelSpacing in one slice": (
        _series(_set_raw(0x00280030, "DS", "0\\1"), which=2),
        "slice2.dcm: PixelSpacing"),
    "series BitsAllocated 32 over 16-bit data": (
        _series(_set("BitsAllocated", 32)), "inconsistent pixel data size"),
    "series BitsAllocated 32 in one slice": (
        _series(_set("BitsAllocated", 32), which=3),
        "BitsAllocated (0028,0100)"),
    "series BitsAllocated 12": (_series(_set("BitsAllocated", 12)),
                                "BitsAllocated (0028,0100) is 12"),
    "series BitsStored > BitsAllocated": (_series(_set("BitsStored", 24)),
                                          "BitsStored (0028,0101) is 24"),
    "series pixel data cut in half": (_series(_half_pixels),
                                      "Pixel Data (7FE0,0010) holds 65536 bytes"),
    "series SliceThickness NaN": (_series(_set_raw(0x00180050, "DS", "nan")),
                                  "SliceThickness (0018,0050) is 'nan'"),
    "series SliceThickness negative": (
        _series(_set_raw(0x00180050, "DS", "-4.8")),
        "SliceThickness (0018,0050) is '-4.8'"),
    "series SpacingBetweenSlices inf": (
        _series(_set_raw(0x00180088, "DS", "inf")),
        "SpacingBetweenSlices (0018,0088) is 'inf'"),
    "enhanced frame PixelSpacing NaN": (
        _file(PHILIPS, _frame(6, "PixelMeasuresSequence", 0x00280030, "DS",
                                    "nan\\2.5")),
        "bad.dcm frame 7: PixelSpacing (0028,0030) is 'nan\\2.5'"),
    "enhanced frame PixelSpacing 0": (
        _file(PHILIPS, _frame(0, "PixelMeasuresSequence", 0x00280030, "DS", "0\\0")),
        "frame 1: PixelSpacing (0028,0030) is '0\\0'"),
    "enhanced frame SliceThickness negative": (
        _file(PHILIPS, _frame(3, "PixelMeasuresSequence", 0x00180050, "DS", "-4")),
        "frame 4: SliceThickness (0018,0050) is '-4'"),
    "enhanced frame position NaN": (
        _file(PHILIPS, _frame(9, "PlanePositionSequence", 0x00200032, "DS",
                                    "nan\\0\\0")),
        "frame 10: ImagePositionPatient (0020,0032) is 'nan\\0\\0'"),
    "enhanced frame RescaleSlope 0": (
        _file(PHILIPS, _frame(4, "PixelValueTransformationSequence", 0x00281053,
                                    "DS", "0")),
        "frame 5: RescaleSlope (0028,1053) is 0"),
    "enhanced BitsAllocated 32 over 16-bit data": (
        _file(PHILIPS, _set("BitsAllocated", 32)), "inconsistent pixel data size"),
    "enhanced pixel data cut in half": (_file(PHILIPS, _half_pixels),
                                        "holds 368640 bytes"),
    "mosaic PixelSpacing 0": (_file(MOSAIC, _set_raw(0x00280030, "DS", "0\\2.4")),
                              "bad.IMA: PixelSpacing (0028,0030) is '0\\2.4'"),
    "mosaic SpacingBetweenSlices NaN": (
        _file(MOSAIC, _set_raw(0x00180088, "DS", "nan")),
        "SpacingBetweenSlices (0018,0088) is 'nan'"),
    "mosaic BitsAllocated 32 over 16-bit data": (
        _file(MOSAIC, _set("BitsAllocated", 32)), "inconsistent pixel data size"),
    "mosaic not dividing into tiles": (_file(MOSAIC, _set("Columns", 719)),
                                       "do not divide"),
}


@pytest.mark.parametrize("case", list(BAD_TAGS))
def test_impossible_tags_are_refused_naming_the_file_and_the_tag(tmp_path, case, capsys):
    from core.cli import main

    make, words = BAD_TAGS[case]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        path = make(tmp_path)
    with pytest.raises(DataFileError) as err:
        load_volume(path)
    text = str(err.value)
    assert "\n" not in text and words in text, text
    # the CLI says the same in one line, exit 2, no traceback
    rc = main(["segment", "--model", "m.npz", "--points", "p.csv", "--image", str(path),
               "--out", str(tmp_path / "o.nii")])
    err_text = capsys.readouterr().err
    assert rc == 2 and words in err_text and len(err_text.strip().splitlines()) == 1


@pytest.mark.parametrize("source", [PHILIPS, MOSAIC], ids=["philips enhanced", "siemens mosaic"])
def test_real_one_file_volumes_read_the_same_in_implicit_vr(tmp_path, source):
    """PACS and anonymisers often rewrite files as implicit VR (the VRs then come from the
    dictionary): the same voxels at the same places."""
    ds = _read(source)
    ds.file_meta.TransferSyntaxUID = pydicom.uid.ImplicitVRLittleEndian
    ds.save_as(tmp_path / ("implicit" + source.suffix), implicit_vr=True, little_endian=True)
    ref, vol = load_volume(source), load_volume(tmp_path / ("implicit" + source.suffix))
    assert np.array_equal(vol.data, ref.data) and np.array_equal(vol.affine, ref.affine)
