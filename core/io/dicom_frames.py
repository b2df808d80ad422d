"""One DICOM file holding a whole 3D volume: enhanced multi-frame images and Siemens mosaics.

Enhanced objects (Enhanced MR/CT/PET Image: DICOM PS3.3 C.7.6.16, Multi-frame Functional
Groups) carry each frame's geometry in functional group macros, per frame
(PerFrameFunctionalGroupsSequence) or shared by all frames (SharedFunctionalGroupsSequence):
PlanePositionSequence (ImagePositionPatient), PlaneOrientationSequence
(ImageOrientationPatient), PixelMeasuresSequence (PixelSpacing, SliceThickness) and
PixelValueTransformationSequence (RescaleSlope/Intercept, applied frame by frame). The frames
are sorted along the slice normal and checked like the slices of a series
(:func:`core.io.dicom._check_geometry`). A file holding several volumes (temporal positions,
stacks, echoes, diffusion weightings, or frames repeating a position) is refused with how
many volumes it holds: one 3D volume is what an image is here.

Siemens mosaics (ImageType MOSAIC): the N slices of one volume (NumberOfImagesInMosaic, from
the CSA image header, read by :mod:`nibabel.nicom.csareader`) tiled in one image, a grid of
ceil(sqrt(N)) x ceil(sqrt(N)) tiles in row-major order. ImagePositionPatient is the corner of
the whole tiled image as if it were one slice, so the first slice's first voxel lies
(C - c) / 2 pixels further along the row direction and (R - r) / 2 along the column direction
(R x C: the mosaic's rows and columns, r x c: one tile's). The slices follow the normal
row x column, with the sign of the CSA's SliceNormalVector, SpacingBetweenSlices apart (else
SliceThickness).

Both are placed as dcm2niix (nii_dicom.c) and nibabel (nicom.dicomwrappers.MosaicWrapper) place
them: voxel (i, j, k) is column i, row j of the k-th slice along the normal, at
LPS = position + i dx row + j dy column + k dz normal, with (dy, dx) = PixelSpacing; the RAS
affine is that with x and y negated (:func:`core.io.itk_image.affine_from_itk`). pydicom parses
the headers and decodes the pixels (imported only for these files: it takes about 0.5 s).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from core.errors import DataFileError, why
from core.io.dicom import (
    NATIVE_SYNTAXES,
    TRANSFER_SYNTAXES,
    _check_geometry,
    _finite_floats,
    check_image_tags,
    check_pixel_data_size,
)
from core.io.itk_image import affine_from_itk
from core.io.limits import check_declared_size
from core.types.volume import Volume

# Text-valued VRs whose raw bytes are the tag's text ("nan\\1" stays as written).
_TEXT_VRS = {"DS", "IS", "CS", "UI", "LO", "SH", "ST", "LT", "AS", "DA", "TM", "DT", "PN"}


def _read_dataset(path: Path, where: Path):
    """The pydicom dataset of ``path``, pixel data deferred (read when decoded)."""
    try:
        import pydicom
    except ImportError:
        raise DataFileError(where, f"{path.name} holds a whole volume in one file (enhanced "
                                   "multi-frame or mosaic), which needs pydicom: pip install "
                                   "pydicom") from None

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return pydicom.dcmread(path, defer_size="256 KB")
    except Exception as exc:  # noqa: BLE001  (pydicom raises many types on damaged files)
        raise DataFileError(where, f"{path.name}: cannot parse the DICOM header "
                                   f"({why(exc, path)})") from None


def _text(ds) -> Callable[[str], str]:
    """A tag-text getter ('gggg|eeee' -> text, '' when absent) on a pydicom dataset or item.

    Text VRs are taken from the raw bytes, so that an impossible value ("nan", "-1") reaches
    :func:`core.io.dicom.check_image_tags` as written rather than as pydicom's conversion.
    """
    from pydicom.datadict import dictionary_VR

    def tag(key: str) -> str:
        group, element = (int(part, 16) for part in key.split("|"))
        try:
            raw = ds.get_item((group, element))
            if raw is None:
                return ""
            vr = raw.VR or dictionary_VR((group, element))
            if isinstance(raw.value, bytes) and vr in _TEXT_VRS:
                return raw.value.decode("latin-1").strip("\0 ")
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                value = ds[(group, element)].value
        except Exception:  # noqa: BLE001  (a value pydicom cannot convert: absent for us)
            return ""
        if value is None:
            return ""
        if isinstance(value, (list, tuple)) or type(value).__name__ == "MultiValue":
            return "\\".join(str(v) for v in value)
        return str(value).strip()

    return tag


def _checked_floats(text: str) -> np.ndarray:
    """The numbers of a spacing tag that :func:`check_image_tags` has accepted."""
    values = _finite_floats(text)
    if values is None:
        raise ValueError(f"spacing '{text}' was not checked by check_image_tags")
    return values


def _vector(text: str, count: int, what: str, name: str, where: Path) -> np.ndarray:
    values = _finite_floats(text) if text else None
    if values is None or values.size != count or not np.all(np.isfinite(values)):
        raise DataFileError(where, f"{name}: {what} is '{text}', not {count} finite numbers")
    return values


def _orientation(text: str, name: str, where: Path) -> tuple[np.ndarray, np.ndarray]:
    """Row and column direction cosines of an ImageOrientationPatient text (checked)."""
    ori = _vector(text, 6, "ImageOrientationPatient (0020,0037)", name, where)
    row, col = ori[:3], ori[3:]
    if not (np.isclose(np.linalg.norm(row), 1, atol=1e-3) and
            np.isclose(np.linalg.norm(col), 1, atol=1e-3) and abs(row @ col) < 1e-3):
        raise DataFileError(where, f"{name}: ImageOrientationPatient (0020,0037) is '{text}', "
                                   "not two orthogonal unit vectors")
    return row, col


def _pixels(ds, path: Path, where: Path, frames: int) -> np.ndarray:
    """The stored pixel values, (frames, rows, columns), decoded by pydicom (checked first)."""
    from pydicom.pixels import get_decoder

    tag = _text(ds)
    syntax = str(getattr(ds.file_meta, "TransferSyntaxUID", "") or "1.2.840.10008.1.2")
    samples = int(tag("0028|0002") or 1)
    if samples != 1:
        raise DataFileError(where, f"{path.name}: {samples} samples per pixel (a colour "
                                   "image), a scalar image is needed")
    rows, cols, bits = (int(tag(key) or 0) for key in ("0028|0010", "0028|0011", "0028|0100"))
    if not (rows and cols and bits):
        raise DataFileError(where, f"{path.name}: Rows, Columns or BitsAllocated missing: the "
                                   "pixel data's size is unknown")
    element = ds.get_item(0x7FE00010)
    if element is None:
        raise DataFileError(where, f"{path.name} has no Pixel Data (7FE0,0010)")
    if syntax in NATIVE_SYNTAXES:
        check_pixel_data_size(path, syntax, rows, cols, frames, 1, bits, where,
                              length=int(getattr(element, "length", None) or len(element.value)))
    try:
        decodable = get_decoder(syntax).is_available
    except Exception:  # noqa: BLE001  (no decoder at all for this syntax)
        decodable = False
    if not decodable:
        label = TRANSFER_SYNTAXES.get(syntax, (syntax, False))[0]
        raise DataFileError(where, f"{path.name} is compressed as '{label}' ({syntax}), which "
                                   "pydicom cannot decode here (install pylibjpeg and "
                                   "pylibjpeg-libjpeg, or convert the file to explicit VR little "
                                   "endian first)")
    check_declared_size(path, rows * cols * frames * max(bits // 8, 1),
                        f"{frames} frames of {rows} x {cols} pixels",
                        max_ratio=1.0 if syntax in NATIVE_SYNTAXES else float("inf"))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            data = ds.pixel_array
    except Exception as exc:  # noqa: BLE001
        raise DataFileError(where, f"{path.name}: cannot decode the pixel data "
                                   f"({why(exc, path)})") from None
    return data.reshape(frames, rows, cols)


def _rescaled(data: np.ndarray, slopes: np.ndarray, intercepts: np.ndarray) -> np.ndarray:
    """Stored values as real values, frame by frame (float32 unless the scaling is identity)."""
    if np.all(slopes == 1) and np.all(intercepts == 0):
        return data
    return data.astype(np.float32) * slopes.astype(np.float32)[:, None, None] \
        + intercepts.astype(np.float32)[:, None, None]


def _rescale_of(tag: Callable[[str], str], name: str, where: Path,
                default: tuple[float, float] = (1.0, 0.0)) -> tuple[float, float]:
    """(slope, intercept) from RescaleSlope (0028,1053) / RescaleIntercept (0028,1052)."""
    slope_text, intercept_text = tag("0028|1053"), tag("0028|1052")
    slope = _vector(slope_text, 1, "RescaleSlope (0028,1053)", name, where)[0] \
        if slope_text else default[0]
    intercept = _vector(intercept_text, 1, "RescaleIntercept (0028,1052)", name, where)[0] \
        if intercept_text else default[1]
    if slope == 0:
        raise DataFileError(where, f"{name}: RescaleSlope (0028,1053) is 0: every voxel "
                                   "would be the intercept")
    return float(slope), float(intercept)


def _volume(data_frames: np.ndarray, row: np.ndarray, col: np.ndarray, normal: np.ndarray,
            origin: np.ndarray, spacing: tuple[float, float, float], where: Path) -> Volume:
    """A Volume from frames (k, rows, columns) sorted along ``normal`` and the LPS geometry."""
    affine = affine_from_itk(origin, spacing, np.column_stack([row, col, normal]))
    return Volume(data=data_frames.transpose(2, 1, 0), affine=affine, path=where)


def _frame_item(frame, shared, keyword: str):
    """A functional group macro's item for one frame: the frame's own, else the shared one."""
    seq = frame.get(keyword) if frame is not None else None
    if not seq and shared is not None:
        seq = shared.get(keyword)
    return seq[0] if seq else None


def read_enhanced(path: Path, where: Path) -> Volume:
    """Read one enhanced multi-frame file holding one 3D volume (see the module docstring)."""
    ds = _read_dataset(path, where)
    name = path.name
    top = _text(ds)
    check_image_tags(top, name, where)
    frames_text = top("0028|0008")
    n = int(frames_text) if frames_text.isdigit() else 1
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    if not per_frame:
        raise DataFileError(where, f"{name} is a multi-frame image ({n} frames) without "
                                   "per-frame functional groups (not an enhanced image): its "
                                   "frames' positions are unknown")
    if len(per_frame) != n:
        raise DataFileError(where, f"{name}: NumberOfFrames (0028,0008) is {n} but the "
                                   f"PerFrameFunctionalGroupsSequence has {len(per_frame)} items")
    shared_seq = ds.get("SharedFunctionalGroupsSequence")
    shared = shared_seq[0] if shared_seq else None
    top_rescale = _rescale_of(top, name, where)
    positions, orientations, slopes, intercepts = [], [], [], []
    spacings: set[str] = set()
    kinds: dict[str, set[str]] = {"temporal positions": set(), "stacks": set(),
                                  "echo times": set(), "b-values": set()}
    for index, frame in enumerate(per_frame):
        label = f"{name} frame {index + 1}"
        plane = _frame_item(frame, shared, "PlanePositionSequence")
        orient = _frame_item(frame, shared, "PlaneOrientationSequence")
        measures = _frame_item(frame, shared, "PixelMeasuresSequence")
        if plane is None or orient is None or measures is None:
            missing = [k for k, v in (("PlanePositionSequence", plane),
                                      ("PlaneOrientationSequence", orient),
                                      ("PixelMeasuresSequence", measures)) if v is None]
            raise DataFileError(where, f"{label} has no {' or '.join(missing)} (per frame or "
                                       "shared): its geometry is unknown")
        positions.append(_vector(_text(plane)("0020|0032"), 3,
                                 "ImagePositionPatient (0020,0032)", label, where))
        orientations.append(np.concatenate(_orientation(_text(orient)("0020|0037"), label,
                                                        where)))
        measure_tag = _text(measures)
        check_image_tags(measure_tag, label, where)
        if not measure_tag("0028|0030"):
            raise DataFileError(where, f"{label}: no PixelSpacing (0028,0030) in its "
                                       "PixelMeasuresSequence: the pixel size is unknown")
        spacings.add(measure_tag("0028|0030"))
        transform = _frame_item(frame, shared, "PixelValueTransformationSequence")
        slope, intercept = _rescale_of(_text(transform), label, where, top_rescale) \
            if transform is not None else top_rescale
        slopes.append(slope)
        intercepts.append(intercept)
        content = _frame_item(frame, None, "FrameContentSequence")
        if content is not None:
            ctag = _text(content)
            kinds["temporal positions"].add(ctag("0020|9128"))
            kinds["stacks"].add(ctag("0020|9056"))
        echo = _frame_item(frame, shared, "MREchoSequence")
        kinds["echo times"].add(_text(echo)("0018|9082") if echo is not None else "")
        diffusion = _frame_item(frame, shared, "MRDiffusionSequence")
        kinds["b-values"].add(_text(diffusion)("0018|9087") if diffusion is not None else "")
    positions_arr, orientations_arr = np.array(positions), np.array(orientations)
    _refuse_4d(positions_arr, kinds, n, name, where)
    if len(spacings) > 1:
        raise DataFileError(where, f"{name}: the frames' PixelSpacing differs "
                                   f"({', '.join(sorted(spacings))}): not one 3D grid")
    order = _check_geometry(positions_arr, orientations_arr,
                            [f"frame {i + 1}" for i in range(n)], where, unit="frames",
                            tilt=top("0018|1120"))
    order = np.arange(n) if order is None else order
    data = _pixels(ds, path, where, n)[order]
    data = _rescaled(data, np.array(slopes)[order], np.array(intercepts)[order])
    positions_arr = positions_arr[order]
    row, col = orientations_arr[0, :3], orientations_arr[0, 3:]
    normal = np.cross(row, col)
    gap = float(np.median(np.diff(positions_arr, axis=0) @ normal))
    dy, dx = _checked_floats(spacings.pop())
    return _volume(data, row, col, normal, positions_arr[0], (dx, dy, gap), where)


def _refuse_4d(positions: np.ndarray, kinds: dict[str, set[str]], n: int, name: str,
               where: Path) -> None:
    """Refuse an enhanced file holding several volumes, saying how many and along what."""
    n_positions = len(np.unique(np.round(positions, 2), axis=0))
    several = {kind: len(values - {""}) for kind, values in kinds.items()
               if len(values - {""}) > 1}
    if n_positions == n and not several:
        return
    volumes = n // n_positions if n_positions < n else max(several.values())
    along = ", ".join(f"{count} {kind}" for kind, count in several.items())
    raise DataFileError(where, f"{name} holds 4D data, {volumes} volumes: {n} frames at "
                               f"{n_positions} slice positions{f' ({along})' if along else ''}; "
                               "one 3D volume is read: split it into 3D volumes first (e.g. "
                               "dcm2niix)")


def _csa_image_header(ds, name: str, where: Path) -> dict:
    """The tags of a Siemens CSA image header (0029,xx10), parsed by nibabel ({} if absent)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # nibabel.nicom's "experimental" notice
        from nibabel.nicom import csareader
    raw = None
    try:
        raw = ds.private_block(0x0029, "SIEMENS CSA HEADER")[0x10].value
    except (KeyError, ValueError):
        element = ds.get((0x0029, 0x1010))
        raw = element.value if element is not None else None
    if not raw:
        return {}
    try:
        return csareader.read(raw)["tags"]
    except Exception as exc:  # noqa: BLE001  (a damaged CSA header: CSAReadError, struct.error)
        raise DataFileError(where, f"{name}: cannot parse the Siemens CSA image header "
                                   f"(0029,1010) ({why(exc)})") from None


def _csa_values(csa: dict, key: str) -> list:
    entry = csa.get(key) or {}
    return list(entry.get("items") or [])


def read_mosaic(path: Path, where: Path) -> Volume:
    """Read one Siemens mosaic file: its tiles are the slices of one 3D volume."""
    ds = _read_dataset(path, where)
    name = path.name
    tag = _text(ds)
    check_image_tags(tag, name, where)
    csa = _csa_image_header(ds, name, where)
    count = _csa_values(csa, "NumberOfImagesInMosaic")
    n_text = str(count[0]) if count else tag("0019|100a")
    n_value = _finite_floats(n_text) if n_text else None
    if n_value is None or n_value.size != 1 or not float(n_value[0]).is_integer() \
            or n_value[0] < 1:
        raise DataFileError(where, f"{name} is a Siemens mosaic without a valid "
                                   "NumberOfImagesInMosaic in its CSA header: its slices cannot "
                                   "be told apart")
    n = int(n_value[0])
    if n < 2:
        raise DataFileError(where, f"{name} is a Siemens mosaic of a single slice: a 3D image "
                                   "needs at least two")
    tiles = math.ceil(math.sqrt(n))
    mosaic_rows, mosaic_cols = int(tag("0028|0010") or 0), int(tag("0028|0011") or 0)
    if mosaic_rows % tiles or mosaic_cols % tiles or not mosaic_rows:
        raise DataFileError(where, f"{name}: a mosaic of {n} slices is a grid of {tiles} x "
                                   f"{tiles} tiles, but its {mosaic_rows} x {mosaic_cols} pixels "
                                   "do not divide into it")
    rows, cols = mosaic_rows // tiles, mosaic_cols // tiles
    row, col = _orientation(tag("0020|0037"), name, where)
    corner = _vector(tag("0020|0032"), 3, "ImagePositionPatient (0020,0032)", name, where)
    if not tag("0028|0030"):
        raise DataFileError(where, f"{name}: no PixelSpacing (0028,0030): the pixel size is "
                                   "unknown")
    dy, dx = _checked_floats(tag("0028|0030"))
    normal = np.cross(row, col)
    csa_normal = _csa_values(csa, "SliceNormalVector")
    if len(csa_normal) == 3:
        vector = np.asarray(csa_normal, dtype=np.float64)
        length = float(np.linalg.norm(vector))
        agree = float(normal @ vector) / length if length > 0 else 0.0
        if not np.isfinite(agree) or abs(abs(agree) - 1) > 1e-3:
            raise DataFileError(where, f"{name}: the CSA SliceNormalVector {csa_normal} is not "
                                       "along the normal of ImageOrientationPatient")
        if agree < 0:
            normal = -normal
    gap = 0.0
    for key in ("0018|0088", "0018|0050"):  # SpacingBetweenSlices, else SliceThickness
        if tag(key):
            gap = float(_checked_floats(tag(key))[0])
            if gap > 0:
                break
    if gap <= 0:
        raise DataFileError(where, f"{name}: neither SpacingBetweenSlices (0018,0088) nor "
                                   "SliceThickness (0018,0050) gives the mosaic's slice "
                                   "spacing")
    # The position names the corner of the whole tiled image: shift to the first tile's.
    origin = corner + row * dx * (mosaic_cols - cols) / 2 + col * dy * (mosaic_rows - rows) / 2
    mosaic = _pixels(ds, path, where, 1)[0]
    slices = mosaic.reshape(tiles, rows, tiles, cols).transpose(0, 2, 1, 3) \
        .reshape(tiles * tiles, rows, cols)[:n]
    slope, intercept = _rescale_of(tag, name, where)
    data = _rescaled(slices, np.full(n, slope), np.full(n, intercept))
    return _volume(np.ascontiguousarray(data), row, col, normal, origin, (dx, dy, gap), where)
