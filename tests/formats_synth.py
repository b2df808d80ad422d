"""Synthetic images, DICOM series and DICOM objects for the format tests and benchmarks.

Written with SimpleITK (the independent writer of the "same place in the world" tests) or,
for objects SimpleITK cannot write (other transfer syntaxes, multi-frame, structured
reports), byte by byte in explicit VR little endian per DICOM PS3.5/PS3.10.
"""

from __future__ import annotations

import locale
import struct
from pathlib import Path

import numpy as np

from core.geometry.toolkit import rodrigues

MR_IMAGE = "1.2.840.10008.5.1.4.1.1.4"
ENHANCED_MR = "1.2.840.10008.5.1.4.1.1.4.1"
BASIC_TEXT_SR = "1.2.840.10008.5.1.4.1.1.88.11"
EXPLICIT_LE = "1.2.840.10008.1.2.1"
HTJ2K = "1.2.840.10008.1.2.4.201"
UID_ROOT = "1.2.826.0.1.3680043.2.1125.77"


def rotation(axis, degrees: float) -> np.ndarray:
    """Rotation (3, 3) by ``degrees`` about ``axis`` (core.geometry.toolkit's Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return rodrigues(np.radians(degrees) * axis)


def oblique_image(size=(20, 18, 12), spacing=(0.9, 1.3, 2.5), seed: int = 0):
    """A SimpleITK int16 image on an oblique, anisotropic grid with LPS-ordered axes.

    The direction is a rotation of the identity in LPS (i towards patient Left, j towards
    Posterior, as DICOM stores slices), by 17 degrees about an off-axis direction, origin far
    from 0 (scanner coordinates).
    """
    import SimpleITK as sitk

    rng = np.random.default_rng(seed)
    arr = rng.integers(-500, 2000, size=size[::-1]).astype(np.int16)  # [k, j, i]
    image = sitk.GetImageFromArray(arr)
    image.SetSpacing(tuple(float(s) for s in spacing))
    image.SetOrigin((-87.5, 121.25, -40.75))
    image.SetDirection(tuple(rotation((0.3, 0.5, 0.8), 17.0).ravel()))
    return image


def _ds(values) -> str:
    return "\\".join(f"{float(v):.10g}" for v in values)


def write_series(folder: Path, image, uid: str = UID_ROOT + ".1", description: str = "T1 test",
                 positions=None, orientations=None, keep=None, name="IM{:04d}.dcm",
                 patient_name: str = "DOE^JANE", patient_id: str = "PID-12345",
                 compressor: str | None = None) -> list[Path]:
    """Write a 3D SimpleITK image as a DICOM MR series, one file a slice (SimpleITK/GDCM).

    ``positions`` / ``orientations`` (per slice) override the true geometry tags (to make
    tilted, mixed or gapped series); ``keep`` selects which slices are written;
    ``compressor`` writes compressed transfer syntaxes (GDCM's encoders).
    """
    import SimpleITK as sitk

    folder.mkdir(parents=True, exist_ok=True)
    d = np.asarray(image.GetDirection()).reshape(3, 3)
    true_orient = _ds([d[0, 0], d[1, 0], d[2, 0], d[0, 1], d[1, 1], d[2, 1]])
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    if compressor is not None:  # GDCM's encoders: "JPEG", "JPEG2000", "JPEGLS", "RLE"
        writer.SetImageIO("GDCMImageIO")
        writer.UseCompressionOn()
        writer.SetCompressor(compressor)
    files = []
    depth = image.GetDepth()
    # GDCM's DICOM writer leaves the process's LC_CTYPE at "C", which turns Python's default
    # text encoding to ASCII for every later test in the same process: restored afterwards.
    ctype = locale.setlocale(locale.LC_CTYPE)
    try:
        for k in (range(depth) if keep is None else keep):
            piece = image[:, :, k]
            pos = image.TransformIndexToPhysicalPoint((0, 0, int(k))) if positions is None \
                else positions[k]
            tags = {
                "0008|0016": MR_IMAGE, "0008|0018": f"{uid}.{k + 1}", "0008|0060": "MR",
                "0008|103e": description, "0010|0010": patient_name, "0010|0020": patient_id,
                "0020|000d": UID_ROOT + ".100", "0020|000e": uid, "0020|0011": "1",
                "0020|0013": str(int(k) + 1), "0020|0032": _ds(pos),
                "0020|0037": true_orient if orientations is None else _ds(orientations[k]),
                "0018|0050": f"{image.GetSpacing()[2]:.6g}",
            }
            for key, value in tags.items():
                piece.SetMetaData(key, value)
            path = folder / name.format(int(k))
            writer.SetFileName(str(path))
            writer.Execute(piece)
            files.append(path)
    finally:
        locale.setlocale(locale.LC_CTYPE, ctype)
    return files


# -- raw DICOM writer (explicit VR little endian) -------------------------------------------

def _element(group: int, element: int, vr: str, value: bytes) -> bytes:
    if len(value) % 2:
        value += b"\0" if vr in ("UI", "OB") else b" "
    if vr in ("OB", "OW", "OF", "SQ", "UT", "UN"):
        return struct.pack("<HH2sHI", group, element, vr.encode(), 0, len(value)) + value
    return struct.pack("<HH2sH", group, element, vr.encode(), len(value)) + value


def _str(group, element, vr, text: str) -> bytes:
    return _element(group, element, vr, text.encode("ascii"))


def _us(group, element, value: int) -> bytes:
    return _element(group, element, "US", struct.pack("<H", value))


def write_raw_dicom(path: Path, *, sop_class: str = MR_IMAGE, transfer_syntax: str = EXPLICIT_LE,
                    series_uid: str = UID_ROOT + ".9", instance: int = 1, rows: int = 8,
                    cols: int = 8, frames: int = 1, position=(0.0, 0.0, 0.0),
                    pixels: bool = True, encapsulated: bool = False) -> Path:
    """A minimal DICOM Part 10 file written byte by byte (no DICOM library involved)."""
    sop_uid = f"{series_uid}.{instance}"
    meta_body = (_element(0x0002, 0x0001, "OB", b"\0\1") + _str(0x0002, 0x0002, "UI", sop_class)
                 + _str(0x0002, 0x0003, "UI", sop_uid) + _str(0x0002, 0x0010, "UI", transfer_syntax)
                 + _str(0x0002, 0x0012, "UI", UID_ROOT + ".0"))
    meta = _element(0x0002, 0x0000, "UL", struct.pack("<I", len(meta_body))) + meta_body
    data = (_str(0x0008, 0x0016, "UI", sop_class) + _str(0x0008, 0x0018, "UI", sop_uid)
            + _str(0x0008, 0x0060, "CS", "SR" if not pixels else "MR")
            + _str(0x0010, 0x0010, "PN", "DOE^JANE") + _str(0x0010, 0x0020, "LO", "PID-12345")
            + _str(0x0020, 0x000D, "UI", UID_ROOT + ".100") + _str(0x0020, 0x000E, "UI", series_uid)
            + _str(0x0020, 0x0013, "IS", str(instance)))
    if pixels:
        data += (_str(0x0020, 0x0032, "DS", _ds(position))
                 + _str(0x0020, 0x0037, "DS", "1\\0\\0\\0\\1\\0")
                 + _us(0x0028, 0x0002, 1) + _str(0x0028, 0x0004, "CS", "MONOCHROME2"))
        if frames > 1:
            data += _str(0x0028, 0x0008, "IS", str(frames))
        data += (_us(0x0028, 0x0010, rows) + _us(0x0028, 0x0011, cols)
                 + _str(0x0028, 0x0030, "DS", "1\\1") + _us(0x0028, 0x0100, 16)
                 + _us(0x0028, 0x0101, 16) + _us(0x0028, 0x0102, 15) + _us(0x0028, 0x0103, 1))
        raw = (np.arange(rows * cols * frames, dtype=np.int16) % 100).tobytes()
        if encapsulated:  # undefined length: basic offset table item, one fragment, delimiter
            fragment = b"\xff\x4f\xff\x51" + raw[:64]  # a codestream start, then garbage
            body = (struct.pack("<HHI", 0xFFFE, 0xE000, 0)
                    + struct.pack("<HHI", 0xFFFE, 0xE000, len(fragment)) + fragment
                    + struct.pack("<HHI", 0xFFFE, 0xE0DD, 0))
            data += struct.pack("<HH2sHI", 0x7FE0, 0x0010, b"OB", 0, 0xFFFFFFFF) + body
        else:
            data += _element(0x7FE0, 0x0010, "OW", raw)
    else:
        data += _str(0x0040, 0xA040, "CS", "CONTAINER")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\0" * 128 + b"DICM" + meta + data)
    return path
