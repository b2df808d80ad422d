"""Shape models: the versioned ``.npz`` format (``ssm-studio-model``) of :func:`save_model`."""

from __future__ import annotations

import json
import os
import zlib
from pathlib import Path
from typing import cast

import numpy as np

from core.errors import DataFileError, require_file, why
from core.io.atomic import atomic_path, json_default
from core.io.registry import FileFormat, lookup, register, split_member
from core.models.shape_model import ShapeModel

MODEL_FORMAT = "ssm-studio-model"
MODEL_FORMAT_VERSION = 1


def save_model(path: str | os.PathLike, model: ShapeModel) -> None:
    """Write a shape model as ``.npz`` (format ``ssm-studio-model``, version 1).

    File layout (all arrays float64 unless stated):

    ============== ============ =====================================================
    key            shape        meaning
    ============== ============ =====================================================
    header         () str       JSON: format, format_version, units ("mm"), method,
                                params, source_meshes, n_vertices, n_factors, info
                                (free-form metadata: timings, evaluation, ...)
    mean           (N, 3)       mean shape, model frame, mm
    factors        (M, N, 3)    deformation factors
    coef_var       (M,)         prior variance of each coefficient
    faces          (F, 3) int64 triangles
    world_transform (4, 4)      model frame -> world RAS mm
    ============== ============ =====================================================
    """
    path = Path(path)
    fmt = lookup(path, "model")
    if fmt is not None and fmt.write is not None and fmt.write is not save_model:
        return fmt.write(path, model)  # another format (statismo .h5, core.io.statismo)
    header = {
        "format": MODEL_FORMAT,
        "format_version": MODEL_FORMAT_VERSION,
        "units": "mm",
        "method": model.method,
        "params": model.params,
        "source_meshes": list(model.source_meshes),
        "n_vertices": model.n_vertices,
        "n_factors": model.n_factors,
        "info": model.info,
    }
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(
                fh,
                header=np.array(json.dumps(header, default=json_default)),
                mean=model.mean, factors=model.factors, coef_var=model.coef_var,
                faces=model.faces, world_transform=model.world_transform,
            )


def load_model(path: str | os.PathLike) -> ShapeModel:
    """Read a model written by :func:`save_model`, checking format, version and shapes.

    Raises
    ------
    DataFileError
        Not found, not an npz, missing header or arrays, unknown format or version,
        inconsistent shapes, non-finite values.

    ``FILE#MEMBER`` names one model of a file that holds several (statismo catalogs,
    :func:`core.io.registry.split_member`); an ``.npz`` holds one model.
    """
    file, member = split_member(path)
    file = require_file(file)
    fmt = lookup(file, "model")
    if fmt is not None and fmt.read is not None and fmt.read is not load_model:
        return cast(ShapeModel, fmt.read(path if member is not None else file))  # e.g. statismo .h5
    if member is not None:
        raise DataFileError(file, f"'#{member}' names a model inside the file, but an .npz "
                                  "file holds one model")
    path = file
    arrays = _read_arrays(path)
    header = _read_header(path, arrays)
    _check_arrays(path, header, arrays)
    try:
        model = ShapeModel(
            mean=arrays["mean"], factors=arrays["factors"], coef_var=arrays["coef_var"],
            faces=arrays["faces"], world_transform=arrays["world_transform"],
            method=str(header.get("method", "unknown")), params=dict(header.get("params", {})),
            source_meshes=[str(m) for m in header.get("source_meshes", [])],
            info=dict(header.get("info", {})),
        )
    except (ValueError, TypeError) as exc:
        raise DataFileError(path, f"inconsistent model: {exc}") from None
    for key, expected in (("n_vertices", model.n_vertices), ("n_factors", model.n_factors)):
        if key in header and header[key] != expected:
            raise DataFileError(path, f"inconsistent model: header says {key}={header[key]} but "
                                      f"the arrays hold {expected}")
    return model


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every array of the model's ``.npz`` (members checked against the file size first)."""
    import zipfile

    with open(path, "rb") as fh:
        if fh.read(4) != b"PK\x03\x04":
            raise DataFileError(path, "not a shape model file (not an .npz archive)")
    try:
        _check_members(path)
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except DataFileError:
        raise
    except (zipfile.BadZipFile, EOFError, zlib.error, OSError, NotImplementedError) as exc:
        raise DataFileError(path, f"not a shape model file: truncated or corrupt .npz archive "
                                  f"({why(exc, path)})") from None
    except ValueError as exc:  # object arrays (pickles) are refused, or a malformed array
        raise DataFileError(path, f"not a shape model file ({why(exc, path)})") from None
    except MemoryError:
        raise DataFileError(path, "not enough memory to read this model") from None
    return arrays


def _read_header(path: Path, arrays: dict[str, np.ndarray]) -> dict:
    """The model's JSON header, checked for format and version."""
    if "header" not in arrays:
        raise DataFileError(path, "not a shape model file (no header)")
    if arrays["header"].dtype.kind not in "US" or arrays["header"].ndim != 0:
        raise DataFileError(path, "model header is not a JSON text")
    try:
        header = json.loads(str(arrays["header"]))
    except json.JSONDecodeError:
        raise DataFileError(path, "model header is not valid JSON") from None
    except RecursionError:
        raise DataFileError(path, "model header is nested too deeply to be read") from None
    if not isinstance(header, dict):
        raise DataFileError(path, "model header is not a JSON object")
    if header.get("format") != MODEL_FORMAT:
        raise DataFileError(path, f"not an SSM Studio model (format '{header.get('format')}')")
    version = header.get("format_version")
    if version is None:
        raise DataFileError(path, "model header has no format_version")
    if version != MODEL_FORMAT_VERSION:
        raise DataFileError(path, f"model format version {version} is not supported "
                                  f"(this SSM Studio reads version {MODEL_FORMAT_VERSION})")
    return header


def _check_arrays(path: Path, header: dict, arrays: dict[str, np.ndarray]) -> None:
    """Arrays present, of real numbers, and a proper affine world transform; header fields
    of the right JSON types."""
    missing = [k for k in ("mean", "factors", "coef_var", "faces", "world_transform")
               if k not in arrays]
    if missing:
        raise DataFileError(path, f"model file lacks arrays: {', '.join(missing)}")
    for key in ("params", "info"):
        if not isinstance(header.get(key, {}), dict):
            raise DataFileError(path, f"model header field '{key}' is not a JSON object")
    if not isinstance(header.get("source_meshes", []), list):
        raise DataFileError(path, "model header field 'source_meshes' is not a list")
    if header.get("units", "mm") != "mm":
        raise DataFileError(path, f"model units are '{header.get('units')}', only mm is supported")
    if arrays["faces"].dtype.kind not in "iu":
        raise DataFileError(path, f"model faces must be integers, got {arrays['faces'].dtype}")
    for key in ("mean", "factors", "coef_var", "world_transform"):
        if arrays[key].dtype.kind not in "fiu":
            raise DataFileError(path, f"model array '{key}' must hold real numbers, got "
                                      f"{_dtype_name(arrays[key].dtype)}")
    transform = arrays["world_transform"]
    if transform.shape == (4, 4) and np.all(np.isfinite(transform)):
        if abs(np.linalg.det(transform[:3, :3].astype(np.float64))) < 1e-12:
            raise DataFileError(path, "the model's world_transform is singular (it maps the "
                                      "model onto a plane or a point)")
        if not np.allclose(transform[3], [0, 0, 0, 1]):
            raise DataFileError(path, "the model's world_transform is not affine (last row "
                                      "must be 0 0 0 1)")


def _dtype_name(dtype: np.dtype) -> str:
    kinds = {"c": "complex numbers", "U": "text", "S": "bytes", "O": "Python objects",
             "b": "booleans", "V": "records", "M": "dates", "m": "time spans"}
    return kinds.get(dtype.kind, str(dtype))


_SUSPICIOUS_RATIO = 200  # float model data compress ~1.1-3x; zeros by ~1000x
_SUSPICIOUS_SIZE = 16 << 20


def _check_members(path: Path) -> None:
    """Check every member's declared size before numpy allocates it.

    An .npy member header can claim any shape (1e12 x 3) and a zip member can inflate 1000x
    (a zip bomb): both are refused from the zip directory and the .npy headers alone.
    """
    import zipfile

    from core.io.limits import DEFLATE_MAX_RATIO, check_declared_size

    with zipfile.ZipFile(path) as archive:
        members = archive.infolist()
        total = sum(m.file_size for m in members)
        check_declared_size(path, total, f"{len(members)} arrays",
                            max_ratio=DEFLATE_MAX_RATIO)
        for member in members:
            name = member.filename.removesuffix(".npy")
            if member.file_size > _SUSPICIOUS_SIZE and \
                    member.file_size > _SUSPICIOUS_RATIO * max(member.compress_size, 1):
                raise DataFileError(path, f"array '{name}' inflates from "
                                          f"{member.compress_size} to {member.file_size} bytes "
                                          "(a zip bomb?), not read")
            with archive.open(member) as fh:
                try:
                    version = np.lib.format.read_magic(fh)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                    else:
                        shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
                except (ValueError, SyntaxError, TypeError, OverflowError) as exc:
                    raise DataFileError(path, f"array '{name}' has a corrupt header "
                                              f"({why(exc)})") from None
            if dtype.hasobject:
                raise DataFileError(path, f"not a shape model file (array '{name}' holds "
                                          "Python objects, a pickle: not read, "
                                          "allow_pickle=False)")
            declared = int(np.prod([int(s) for s in shape], dtype=object)) * dtype.itemsize
            if declared > member.file_size:
                raise DataFileError(path, f"array '{name}' declares shape {tuple(shape)} "
                                          f"({declared} bytes) but its member holds "
                                          f"{member.file_size} bytes: corrupt")


register(FileFormat(".npz", "model", "SSM Studio shape model", read=load_model, write=save_model))
