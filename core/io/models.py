"""Shape models: the versioned ``.npz`` format (``ssm-studio-model``) of :func:`save_model`."""

from __future__ import annotations

import json
import os
import zlib
from pathlib import Path

import numpy as np

from core.io.atomic import atomic_path, json_default
from core.io.errors import DataFileError, require_file, why
from core.io.registry import FileFormat, lookup, register
from core.shape_model import ShapeModel

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
    """
    import zipfile

    path = require_file(path)
    fmt = lookup(path, "model")
    if fmt is not None and fmt.read is not None and fmt.read is not load_model:
        return fmt.read(path)  # another format (statismo .h5, core.io.statismo)
    with open(path, "rb") as fh:
        if fh.read(4) != b"PK\x03\x04":
            raise DataFileError(path, "not a shape model file (not an .npz archive)")
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (zipfile.BadZipFile, EOFError, zlib.error, OSError) as exc:
        raise DataFileError(path, f"not a shape model file: truncated or corrupt .npz archive "
                                  f"({why(exc, path)})") from None
    except ValueError as exc:  # object arrays (pickles) are refused, or a malformed array
        raise DataFileError(path, f"not a shape model file ({why(exc, path)})") from None
    if "header" not in arrays:
        raise DataFileError(path, "not a shape model file (no header)")
    try:
        header = json.loads(str(arrays["header"]))
    except json.JSONDecodeError:
        raise DataFileError(path, "model header is not valid JSON") from None
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


register(FileFormat(".npz", "model", "SSM Studio shape model", read=load_model, write=save_model))
