"""GUI side of the clinical formats (no Qt): file-dialog filters, the series choice, safe names.

Reading and choosing is :mod:`core.io` (``load_volume`` with ``series=``,
:func:`core.io.dicom.list_series`). A DICOM folder with several series asks the user which
one (``ask``: :func:`app.series_dialog.ask_series` in the window); the choice is remembered as
one file of that series (``load_volume`` on a file reads the file's own series), so a saved
session or a recent file reopens the same series without asking again. Window titles and
messages name a DICOM image by its series description only, never by folder or file name (those
often carry the patient's name or ID).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from core.io import DataFileError, lookup
from core.io.volumes import is_dicom_path

IMAGE_FILTER = ("Images (*.nii *.nii.gz *.nrrd *.nhdr *.mha *.mhd *.dcm);;"
                "NIfTI (*.nii *.nii.gz);;NRRD (*.nrrd *.nhdr);;MetaImage (*.mha *.mhd);;"
                "DICOM (one file of the series) (*.dcm *);;All files (*)")
MODEL_FILTER = "Shape models (*.npz *.h5 *.hdf5);;SSM Studio (*.npz);;statismo/Scalismo (*.h5);;All files (*)"
LABEL_FILTER = ("NIfTI (*.nii.gz *.nii);;3D Slicer segmentation (*.seg.nrrd);;NRRD (*.nrrd);;"
                "MetaImage (*.mha)")


def is_image_path(path: str | os.PathLike) -> bool:
    """Whether ``path`` is opened as an image (a registered image suffix or DICOM)."""
    return lookup(path, "volume") is not None or (Path(path).exists() and is_dicom_path(path))


def is_model_path(path: str | os.PathLike) -> bool:
    return lookup(path, "model") is not None


def resolve_dicom_choice(path: str | os.PathLike, ask: Callable | None,
                         notify: Callable[[str], None] | None = None) -> Path | None:
    """The path to read for ``path``: a DICOM folder with several series becomes one file of
    the series ``ask(series_list)`` returns (None: cancelled); without ``ask`` the series
    with most files is taken and ``notify`` told. Anything else is returned unchanged."""
    return choose_series_file(path, folder_series(path), ask, notify)


def folder_series(path: str | os.PathLike, progress=None) -> list:
    """The image series of a DICOM folder (:func:`core.io.dicom.list_series`; it reads every
    file's header, so a worker calls it: ``progress`` is its Cancel point); [] for anything
    else."""
    from core.io.dicom import list_series

    path = Path(path)
    if not (path.is_dir() and is_dicom_path(path)):
        return []
    if progress is not None:
        progress(0.0, "looking for DICOM series")
    series = list_series(path)
    if progress is not None:
        progress(0.0, "")  # a Cancel while the headers were read stops here
    return series


def choose_series_file(path: str | os.PathLike, series: list, ask: Callable | None,
                       notify: Callable[[str], None] | None = None) -> Path | None:
    """:func:`resolve_dicom_choice` with the folder's ``series`` listed already."""
    path = Path(path)
    if len(series) <= 1:
        return path  # not a DICOM folder, or none (read_dicom explains) or one series
    if ask is None:
        if notify is not None:
            others = "; ".join(s.label() for s in series[1:])
            notify(f"{len(series)} series in the folder, opened the one with most files: "
                   f"{series[0].label()}; others: {others}; pick one with --series UID")
        chosen = series[0]
    else:
        chosen = ask(series)
        if chosen is None:
            return None
    return chosen.files[len(chosen.files) // 2]


def default_series_error(folder: str | os.PathLike, chosen_file: str | os.PathLike,
                         exc: DataFileError) -> DataFileError:
    """``exc`` (reading the series taken by default from ``folder``, as ``chosen_file``),
    naming that series, the folder's other readable series and ``--series``."""
    from core.io.dicom import choose_series, with_other_series

    try:
        chosen = choose_series(chosen_file)
    except (DataFileError, OSError, RuntimeError):
        return exc
    return with_other_series(exc, Path(folder), chosen)


_DISPLAY_NAMES: dict[Path, str] = {}


def remember_display_name(path: str | os.PathLike) -> str:
    """Work out (once, at load time) and cache the safe display name of an opened image."""
    path = Path(path)
    name = path.name
    if path.exists() and is_dicom_path(path):
        try:
            from core.io.dicom import choose_series

            info = choose_series(path)
            what = " ".join(p for p in (info.modality, info.description) if p)
            name = f"DICOM series '{what}'" if what else "DICOM series"
        except (DataFileError, OSError, RuntimeError):
            name = "DICOM series"
    _DISPLAY_NAMES[path] = name
    return name


def display_name(path: str | os.PathLike | None) -> str:
    """A name for titles and messages: the file name, or for DICOM the series description."""
    if path is None:
        return ""
    path = Path(path)
    if path in _DISPLAY_NAMES:
        return _DISPLAY_NAMES[path]
    return "DICOM series" if path.is_dir() or lookup(path, "volume") is None and \
        path.suffix.lower() in ("", ".dcm", ".ima") else path.name
