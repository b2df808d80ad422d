"""Clinical exports of fitted structures for navigation and planning stations: DICOM SEG and
RTSTRUCT referencing the source DICOM series.

- DICOM Segmentation (PS3.3 A.51, Segmentation IOD): one binary segment per structure, name
  and colour (CIELab display colour), written by highdicom (Herrmann et al., "Highdicom: a
  Python library for standardized encoding of image annotations and machine learning model
  outputs in pathology and radiology", J Digit Imaging 2022). Its frames are the source
  series' slices: each frame is the structure's label map sampled at that slice's pixel
  centres (positions from the slice's own ImagePositionPatient / ImageOrientationPatient /
  PixelSpacing, so the SEG sits on the source images whatever order the reader put them in).
- RT Structure Set (PS3.3 A.19): per structure and source slice, the closed planar contours
  of the same masks as the SEG's frames, traced along the pixel edges between inside and
  outside pixels (:func:`mask_contours`), so that a station filling the polygons (pixel centre
  inside) gets back exactly the SEG's pixels; each contour references its slice's SOP
  instance; ROI names and display colours; written with pydicom (rt-utils, the usual helper,
  has had no release since 2023).

Both copy the patient, study and frame-of-reference identifiers of the source series and
get new series and instance UIDs. World RAS (SSM Studio) -> DICOM patient LPS: x and y negated.
"""

from __future__ import annotations

import datetime
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import DataFileError

_LPS = np.array([-1.0, -1.0, 1.0])
RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"
STUDY_COMPONENT_SOP_CLASS = "1.2.840.10008.3.1.2.3.1"  # the usual RTReferencedStudy class


@dataclass(frozen=True)
class ExportStructure:
    """What a clinical export needs of a structure: name, colour, fitted surface (world RAS)."""

    name: str
    color: tuple[float, float, float]
    vertices: np.ndarray
    faces: np.ndarray


def read_series(files: list[Path]) -> list:
    """The source series' headers (pydicom Datasets, pixel data kept: highdicom checks it)."""
    import pydicom

    out = []
    for f in files:
        try:
            out.append(pydicom.dcmread(str(f)))
        except Exception as exc:  # pydicom raises many kinds on a damaged file
            raise DataFileError(f, f"not a readable DICOM file ({type(exc).__name__}: {exc})") \
                from None
    return out


def slice_geometry(ds) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A slice's (origin, row direction, column direction, spacing (row, col)) in world RAS.

    DICOM: ImagePositionPatient is the centre of the first pixel; ImageOrientationPatient's
    first triplet is the direction along a row (increasing column), the second along a column
    (increasing row); PixelSpacing is (between rows, between columns); all LPS.
    """
    origin = np.asarray(ds.ImagePositionPatient, dtype=np.float64) * _LPS
    iop = np.asarray(ds.ImageOrientationPatient, dtype=np.float64)
    along_row, along_col = iop[:3] * _LPS, iop[3:] * _LPS
    spacing = np.asarray(ds.PixelSpacing, dtype=np.float64)
    return origin, along_row, along_col, spacing


def pixel_centres(ds) -> np.ndarray:
    """World RAS centres (Rows, Columns, 3) of a slice's pixels."""
    origin, along_row, along_col, spacing = slice_geometry(ds)
    r = np.arange(int(ds.Rows))[:, None, None] * spacing[0] * along_col
    c = np.arange(int(ds.Columns))[None, :, None] * spacing[1] * along_row
    return origin + r + c


def masks_on_series(label_map: np.ndarray, affine: np.ndarray, datasets: list,
                    values: list[int]) -> np.ndarray:
    """(frames, Rows, Columns, S) bool: label value ``values[s]`` at each slice's pixel centres
    (nearest voxel of ``label_map``, whose voxel -> world RAS matrix is ``affine``)."""
    inverse = np.linalg.inv(np.asarray(affine, dtype=np.float64))
    shape = np.array(label_map.shape)
    out = np.zeros((len(datasets), int(datasets[0].Rows), int(datasets[0].Columns), len(values)),
                   bool)
    for k, ds in enumerate(datasets):
        world = pixel_centres(ds).reshape(-1, 3)
        ijk = np.rint(world @ inverse[:3, :3].T + inverse[:3, 3]).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < shape), axis=1)
        labels = np.zeros(len(world), label_map.dtype)
        labels[ok] = label_map[ijk[ok, 0], ijk[ok, 1], ijk[ok, 2]]
        for s, value in enumerate(values):
            out[k, ..., s] = (labels == value).reshape(int(ds.Rows), int(ds.Columns))
    return out


def _segment_codes(name: str):
    """(category, type) SNOMED CT codes for a structure name (generic when not in pydicom's
    code dictionary: the segment label names it)."""
    from pydicom.sr.codedict import codes

    lowered = name.lower()
    for word, attr in (("caudate", "CaudateNucleus"), ("thalamus", "Thalamus"),
                       ("pallid", "GlobusPallidus"), ("nigra", "SubstantiaNigra"),
                       ("ventricle", "LateralVentricle")):
        if word in lowered:
            return codes.SCT.AnatomicalStructure, getattr(codes.SCT, attr)
    return codes.SCT.AnatomicalStructure, codes.SCT.AnatomicalStructure


def write_dicom_seg(path: str | os.PathLike, structures: list[ExportStructure],
                    masks: np.ndarray, datasets: list) -> Path:
    """DICOM SEG of every structure (``masks[..., s]`` from :func:`masks_on_series`) on the
    source ``datasets`` (module docstring). Structures without a voxel are left out."""
    import highdicom as hd

    from core import __version__
    from core.io.atomic import atomic_path

    keep = [s for s in range(len(structures)) if masks[..., s].any()]
    if not keep:
        raise ValueError("no structure has a voxel on the DICOM series: nothing to export")
    algorithm = hd.AlgorithmIdentificationSequence(
        name="SSM Studio shape model fit", version=__version__,
        family=hd.sr.CodedConcept("123110", "DCM", "Artificial Intelligence"))
    descriptions = []
    for number, s in enumerate(keep, start=1):
        category, kind = _segment_codes(structures[s].name)
        descriptions.append(hd.seg.SegmentDescription(
            segment_number=number, segment_label=structures[s].name[:64],
            segmented_property_category=category, segmented_property_type=kind,
            algorithm_type=hd.seg.SegmentAlgorithmTypeValues.SEMIAUTOMATIC,
            algorithm_identification=algorithm,
            display_color=hd.color.CIELabColor.from_rgb(
                *(int(round(255 * c)) for c in structures[s].color))))
    seg = hd.seg.Segmentation(
        source_images=datasets, pixel_array=masks[..., keep].astype(np.uint8),
        segmentation_type=hd.seg.SegmentationTypeValues.BINARY,
        segment_descriptions=descriptions, series_instance_uid=hd.UID(), series_number=901,
        sop_instance_uid=hd.UID(), instance_number=1, manufacturer="SSM Studio",
        manufacturer_model_name="SSM Studio", software_versions=__version__,
        device_serial_number="0", series_description="SSM Studio structures",
        omit_empty_frames=False)
    path = Path(path)
    with atomic_path(path) as tmp:
        seg.save_as(str(tmp))
    return path


def mask_contours(mask: np.ndarray) -> list[np.ndarray]:
    """Closed contours (each (P, 2), pixel index coordinates (row, column)) of a 2D mask along
    the edges between inside and outside pixels, inside on the left (outer loops
    counter-clockwise in (row, column)); collinear points dropped.

    Corners are kept as doubled integer coordinates. Pieces touching only at a corner are
    traced as one loop through that corner (a figure-eight), which fills to the same pixels.
    """
    m = np.pad(np.asarray(mask, bool), 1)
    inside = np.argwhere(m)
    edges = []
    # (neighbour offset, start corner, end corner) in doubled coordinates about 2 * pixel
    for offset, a, b in (((0, -1), (-1, -1), (1, -1)), ((1, 0), (1, -1), (1, 1)),
                         ((0, 1), (1, 1), (-1, 1)), ((-1, 0), (-1, 1), (-1, -1))):
        nb = inside + offset
        open_side = ~m[nb[:, 0], nb[:, 1]]
        base = 2 * inside[open_side]
        edges += [(tuple(p + a), tuple(p + b)) for p in base]
    outgoing: dict[tuple, list] = {}
    for a, b in edges:
        outgoing.setdefault(a, []).append(b)
    loops = []
    while outgoing:
        start = next(iter(outgoing))
        loop, current = [start], start
        while True:
            choices = outgoing[current]
            nxt = choices.pop(0)
            if not choices:
                del outgoing[current]
            current = nxt
            if current == start:
                break
            loop.append(current)
        pts = np.array(loop, dtype=np.float64)
        d_in, d_out = pts - np.roll(pts, 1, axis=0), np.roll(pts, -1, axis=0) - pts
        turn = d_in[:, 0] * d_out[:, 1] - d_in[:, 1] * d_out[:, 0]
        pts = pts[turn != 0]
        loops.append(pts / 2.0 - 1.0)      # undouble, undo the padding
    return loops


def _image_ref(source):
    """A reference to one source image (ContourImageSequence item)."""
    from pydicom.dataset import Dataset

    ref = Dataset()
    ref.ReferencedSOPClassUID = source.SOPClassUID
    ref.ReferencedSOPInstanceUID = source.SOPInstanceUID
    return ref


def _rtstruct_dataset(datasets: list):
    """The RT Structure Set's header: file meta, the source's patient, study and frame of
    reference, new series and instance UIDs, and the referenced frame/study/series/images."""
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.sequence import Sequence
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, UID, ExplicitVRLittleEndian, generate_uid

    from core import __version__

    first = datasets[0]
    now = datetime.datetime.now()
    sop_uid = generate_uid()
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(RT_STRUCTURE_SET_STORAGE)
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    for key in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyInstanceUID",
                "StudyDate", "StudyTime", "StudyID", "AccessionNumber",
                "ReferringPhysicianName", "FrameOfReferenceUID"):
        setattr(ds, key, getattr(first, key, ""))
    ds.SOPClassUID = RT_STRUCTURE_SET_STORAGE
    ds.SOPInstanceUID = sop_uid
    ds.Modality = "RTSTRUCT"
    ds.SeriesInstanceUID = generate_uid()
    ds.SeriesNumber = 902
    ds.SeriesDescription = "SSM Studio structures"
    ds.InstanceNumber = 1
    ds.Manufacturer = "SSM Studio"
    ds.SoftwareVersions = __version__
    ds.StructureSetLabel = "SSM Studio"
    ds.StructureSetDate = now.strftime("%Y%m%d")
    ds.StructureSetTime = now.strftime("%H%M%S")
    ds.SpecificCharacterSet = "ISO_IR 192"
    series = Dataset()
    series.SeriesInstanceUID = first.SeriesInstanceUID
    series.ContourImageSequence = Sequence([_image_ref(d) for d in datasets])
    study = Dataset()
    study.ReferencedSOPClassUID = STUDY_COMPONENT_SOP_CLASS
    study.ReferencedSOPInstanceUID = first.StudyInstanceUID
    study.RTReferencedSeriesSequence = Sequence([series])
    frame = Dataset()
    frame.FrameOfReferenceUID = first.FrameOfReferenceUID
    frame.RTReferencedStudySequence = Sequence([study])
    ds.ReferencedFrameOfReferenceSequence = Sequence([frame])
    return ds


def write_rtstruct(path: str | os.PathLike, structures: list[ExportStructure],
                   masks: np.ndarray, datasets: list) -> Path:
    """RT Structure Set of every structure's contours (:func:`mask_contours` of
    ``masks[k, ..., s]``, the SEG's frames) on the source ``datasets``."""
    from pydicom.dataset import Dataset
    from pydicom.sequence import Sequence

    from core.io.atomic import atomic_path

    first = datasets[0]
    ds = _rtstruct_dataset(datasets)
    rois, contours, observations = [], [], []
    for number, s in enumerate(structures, start=1):
        roi = Dataset()
        roi.ROINumber = number
        roi.ReferencedFrameOfReferenceUID = first.FrameOfReferenceUID
        roi.ROIName = s.name[:64]
        roi.ROIGenerationAlgorithm = "SEMIAUTOMATIC"
        rois.append(roi)
        items = []
        for k, source in enumerate(datasets):
            origin, along_row, along_col, spacing = slice_geometry(source)
            for rc in mask_contours(masks[k, ..., number - 1]):
                pts = (origin + np.outer(rc[:, 0] * spacing[0], along_col)
                       + np.outer(rc[:, 1] * spacing[1], along_row))
                item = Dataset()
                item.ContourImageSequence = Sequence([_image_ref(source)])
                item.ContourGeometricType = "CLOSED_PLANAR"
                item.NumberOfContourPoints = len(pts)
                item.ContourData = [f"{v:.4f}" for v in (pts * _LPS).reshape(-1)]
                items.append(item)
        roi_contour = Dataset()
        roi_contour.ROIDisplayColor = [int(round(255 * c)) for c in s.color]
        roi_contour.ReferencedROINumber = number
        roi_contour.ContourSequence = Sequence(items)
        contours.append(roi_contour)
        obs = Dataset()
        obs.ObservationNumber = number
        obs.ReferencedROINumber = number
        obs.RTROIInterpretedType = "AVOIDANCE" if "ventricle" in s.name.lower() else "ORGAN"
        obs.ROIInterpreter = ""
        observations.append(obs)
    ds.StructureSetROISequence = Sequence(rois)
    ds.ROIContourSequence = Sequence(contours)
    ds.RTROIObservationsSequence = Sequence(observations)
    path = Path(path)
    with atomic_path(path) as tmp:
        ds.save_as(str(tmp), enforce_file_format=True)
    return path


def export_structures_dicom(folder: str | os.PathLike, structures: list[ExportStructure],
                            label_map: np.ndarray, affine: np.ndarray, series_files: list[Path],
                            stem: str = "structures") -> list[Path]:
    """Every structure as ``<stem>.seg.dcm`` (DICOM SEG) and ``<stem>.rtstruct.dcm``
    (RTSTRUCT), both referencing the source series ``series_files``; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    datasets = read_series(list(series_files))
    for f, ds in zip(series_files, datasets):
        # both objects reference the series' frame of reference (highdicom and the RTSTRUCT IOD
        # require it; the MR and CT image IODs make it type 1, but some exporters drop it)
        if not str(getattr(ds, "FrameOfReferenceUID", "") or ""):
            raise DataFileError(f, "the source series has no Frame of Reference UID, which DICOM "
                                   "SEG and RTSTRUCT must reference")
    masks = masks_on_series(label_map, affine, datasets, list(range(1, len(structures) + 1)))
    return [write_dicom_seg(folder / f"{stem}.seg.dcm", structures, masks, datasets),
            write_rtstruct(folder / f"{stem}.rtstruct.dcm", structures, masks, datasets)]
