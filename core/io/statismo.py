"""statismo / Scalismo shape models (HDF5 ``.h5``), read and written with h5py.

Layout (statismo 0.9+ as statismo and Scalismo write it; Luethi et al., "Statismo - a
framework for PCA based statistical models", Insight Journal 2012):

==================================  ============  ===========================================
path                                shape         meaning
==================================  ============  ===========================================
``model/mean``                      (3N,) f4      mean shape, x1 y1 z1 x2 y2 z2 ...
``model/pcaBasis``                  (3N, M) f4    orthonormal columns U
``model/pcaVariance``               (M,) f4       variances lambda of the components
``model/noiseVariance``             () or (1,)    PPCA noise variance sigma^2 (optional)
``representer/points``              (3, N) f4     the reference mesh's points
``representer/cells``               (3, F) i4     its triangles
``representer`` attributes          ``name`` (itkStandardMeshRepresenter, vtkStandardMesh
                                    Representer), ``datasetType`` (POLYGON_MESH)
``version/majorVersion|minor...``   () int        0.9 (0.8: basis stored as U sqrt(lambda))
``modelinfo/...``                   any           build time, scores, builder info (kept)
==================================  ============  ===========================================

Mapping onto :class:`core.models.shape_model.ShapeModel` (exact): a statismo sample is
``x = mean + U a`` with ``a ~ N(0, diag(lambda))``; ours is ``x = mean + sum_m a_m factor_m``
with ``a ~ N(0, diag(coef_var))``. So ``factors[m] = U[:, m].reshape(N, 3)`` and
``coef_var = lambda``; ``noiseVariance`` goes to ``info["noise_variance"]`` (the fit's
variance floor, :func:`core.reconstruction.fit_points`). Writing the other way, a model
whose factors are not orthonormal (LSF, SPLOCS, varimax) is written by its covariance:
``B = factors diag(sqrt(coef_var))`` (3N x M) has the SVD ``B = U S V^T``, so ``pcaBasis = U``
and ``pcaVariance = S^2`` give the same Gaussian; its own factors are kept beside, in an
``ssmstudio`` group that other tools ignore, and are read back when they still match.

Coordinates: the file holds world coordinates. statismo and Scalismo work in ITK's
physical space, LPS, so by default the mean and basis are read as LPS and the model's
``world_transform`` is diag(-1, -1, 1, 1) (LPS -> RAS); ``space="RAS"`` reads them as RAS.
Our writer writes LPS (and says so in ``ssmstudio`` attributes). Nothing in the file is
executed or unpickled: only numeric datasets and string attributes are read (the VTK
reference of statismo 0.8 files is parsed as mesh data).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from core.io.atomic import atomic_path
from core.errors import DataFileError, require_file
from core.io.registry import FileFormat, register
from core.models.shape_model import ShapeModel

STATISMO_SUFFIXES = (".h5", ".hdf5")
MESH_REPRESENTERS = ("itkStandardMeshRepresenter", "vtkStandardMeshRepresenter")
_LEGACY_REPRESENTERS = ("vtkPolyDataRepresenter", "itkMeshRepresenter")
_FLIP = np.array([-1.0, -1.0, 1.0])
_MODELINFO_LIMIT = 200_000  # elements of one modelinfo dataset kept in the model's info
SPACES = ("LPS", "RAS")


def _h5py():
    import h5py

    return h5py


def _text(value) -> str:
    """An HDF5 string (attribute or dataset value, fixed or variable length) as str."""
    if isinstance(value, np.ndarray):
        value = value.reshape(-1)[0] if value.size else b""
    if isinstance(value, bytes | np.bytes_):
        return value.decode("utf-8", "replace").rstrip("\0")
    return str(value)


def _dataset(path: Path, h5, name: str, *, required: bool = True) -> np.ndarray | None:
    if name not in h5:
        if required:
            raise DataFileError(path, f"not a complete statismo model: no dataset '{name}'")
        return None
    node = h5[name]
    if not isinstance(node, _h5py().Dataset):
        raise DataFileError(path, f"'{name}' is a group, not a dataset")
    if node.dtype.kind not in "iuf":
        raise DataFileError(path, f"'{name}' holds {node.dtype} values, numbers are needed")
    try:
        return np.asarray(node[()], dtype=np.float64)
    except (OSError, ValueError) as exc:
        raise DataFileError(path, f"cannot read '{name}' ({' '.join(str(exc).split())[:200]})") \
            from None


def _version(path: Path, h5, representer: str) -> tuple[int, int]:
    if "version/majorVersion" in h5 and "version/minorVersion" in h5:
        try:
            return int(h5["version/majorVersion"][()]), int(h5["version/minorVersion"][()])
        except (TypeError, ValueError):
            raise DataFileError(path, "version/majorVersion or minorVersion is not an integer") \
                from None
    if representer in _LEGACY_REPRESENTERS:
        return 0, 8
    raise DataFileError(path, "not a complete statismo model: no version/majorVersion and "
                              "version/minorVersion")


def _legacy_reference(path: Path, h5) -> tuple[np.ndarray, np.ndarray]:
    """statismo 0.8's reference mesh: a VTK file stored as bytes in representer/reference."""
    from core.io import load_mesh

    raw = _dataset(path, h5, "representer/reference")
    data = np.asarray(h5["representer/reference"][()]).astype(np.uint8).tobytes() \
        if raw is not None else b""
    with tempfile.TemporaryDirectory() as tmp:
        ref = Path(tmp) / "reference.vtk"
        ref.write_bytes(data)
        try:
            mesh = load_mesh(ref)
        except DataFileError as exc:
            raise DataFileError(path, f"the embedded reference mesh is unreadable "
                                      f"({exc.problem})") from None
    return mesh.vertices, mesh.faces


def _modelinfo(h5) -> dict:
    """modelinfo/ as a JSON-friendly dict (strings, numbers, small arrays), nesting kept."""
    out: dict = {}
    if "modelinfo" not in h5:
        return out

    def visit(group, target: dict) -> None:
        for key, node in group.items():
            if isinstance(node, _h5py().Group):
                visit(node, target.setdefault(key, {}))
            elif node.dtype.kind in "SUO":
                target[key] = _text(node[()])
            elif node.dtype.kind in "iuf" and node.size <= _MODELINFO_LIMIT:
                value = np.asarray(node[()])
                target[key] = value.tolist()
    visit(h5["modelinfo"], out)
    return out


def read_statismo(path: str | os.PathLike, space: str | None = None) -> ShapeModel:
    """Read a statismo/Scalismo triangle-mesh model (.h5) as a :class:`ShapeModel`.

    ``space`` ("LPS" or "RAS") says which world coordinates the file holds; by default
    what our own writer recorded, else LPS (ITK's physical space, as statismo uses).

    Raises
    ------
    DataFileError
        Not HDF5, missing groups or datasets, mismatched shapes, non-finite values, a
        basis that is not orthonormal, or another representer (images, unstructured grids,
        point sets without cells).
    """
    path = require_file(path)
    h5py = _h5py()
    try:
        h5 = h5py.File(path, "r")
    except OSError as exc:
        text = " ".join(str(exc).split())
        problem = "truncated or corrupt HDF5 file" if "signature" not in text else "not an HDF5 file"
        raise DataFileError(path, f"{problem} ({text[:160]})") from None
    with h5:
        return _read_open(path, h5, space)


def _read_open(path: Path, h5, space: str | None) -> ShapeModel:
    """The model in the open statismo file ``h5`` (steps: representer, arrays, info, frame)."""
    if "model" not in h5 or "representer" not in h5:
        if "catalog" in h5:
            raise DataFileError(path, "a statismo model catalog (several models in one file) "
                                      "is not supported: extract one model first")
        raise DataFileError(path, "not a statismo model (no 'model' and 'representer' groups)")
    name = _text(h5["representer"].attrs.get("name", ""))
    points, faces = _representer_mesh(path, h5, name)
    n = len(points)
    major, minor = _version(path, h5, name)
    if (major, minor) not in ((0, 8), (0, 9), (0, 10)) and major != 1:
        raise DataFileError(path, f"statismo format version {major}.{minor} is not supported")
    mean, basis, variance = _pca_arrays(path, h5, points, (major, minor))
    if faces.size == 0 or faces.min() < 0 or faces.max() >= n or \
            np.any(faces != np.rint(faces)):
        raise DataFileError(path, f"representer/cells must index the {n} points (0..{n - 1})")
    keep = variance > max(float(variance.max(initial=0.0)) * 1e-12, 0.0)
    info = _model_info(path, h5, name, (major, minor), keep)
    stored = _ssmstudio_group(path, h5)
    file_space = (space or (stored or {}).get("space") or "LPS").upper()
    if file_space not in SPACES:
        raise DataFileError(path, f"unknown coordinate space '{file_space}' (LPS or RAS)")
    to_world = np.eye(4)
    if file_space == "LPS":
        to_world[:3, :3] = np.diag(_FLIP)
    faces = np.rint(faces).astype(np.int64)
    if stored is not None and space is None:
        model = _stored_model(stored, faces, mean, basis[:, keep], variance[keep], to_world)
        if model is not None:
            model.info.update({k: v for k, v in info.items() if k not in model.info})
            return model
    try:
        return ShapeModel(mean=mean.reshape(n, 3), factors=basis[:, keep].T.reshape(-1, n, 3),
                          coef_var=variance[keep], faces=faces, world_transform=to_world,
                          method="statismo", params={}, source_meshes=[], info=info)
    except ValueError as exc:
        raise DataFileError(path, f"inconsistent model: {exc}") from None


def _representer_mesh(path: Path, h5, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) reference points and (F, 3) triangles of the representer (only triangle
    surfaces can be used: images, point sets, volume and line meshes are refused)."""
    kind = _text(h5["representer"].attrs.get("datasetType", ""))
    if name in _LEGACY_REPRESENTERS:
        return _legacy_reference(path, h5)
    if kind != "POLYGON_MESH" and name not in MESH_REPRESENTERS:
        what = {"IMAGE": "an image (deformation) model", "POINT_SET": "a point-set model "
                "without cells", "VOLUME_MESH": "a volume (tetrahedral) mesh model",
                "LINE_MESH": "a line mesh model"}.get(kind, f"dataset type '{kind or '?'}'")
        raise DataFileError(path, f"{what} (representer '{name or '?'}'): only triangle "
                                  "surface models can be used")
    if kind and kind != "POLYGON_MESH":
        raise DataFileError(path, f"representer '{name}' holds dataset type '{kind}', not "
                                  "a triangle surface (POLYGON_MESH)")
    pts = _dataset(path, h5, "representer/points")
    cells = _dataset(path, h5, "representer/cells", required=False)
    if cells is None:
        raise DataFileError(path, "a point-set model without cells (representer/cells): "
                                  "only triangle surface models can be used")
    if pts.ndim != 2 or pts.shape[0] != 3:
        raise DataFileError(path, f"representer/points must be (3, N), got {pts.shape}")
    if cells.ndim != 2 or cells.shape[0] != 3:
        extra = " (tetrahedra: a volume mesh)" if cells.ndim == 2 and cells.shape[0] == 4 else ""
        raise DataFileError(path, f"representer/cells must be (3, F) triangles, got "
                                  f"{cells.shape}{extra}")
    return pts.T, cells.T


def _pca_arrays(path: Path, h5, points: np.ndarray, version: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The checked (3N,) mean, (3N, M) orthonormal basis and (M,) variances."""
    n = len(points)
    mean = _dataset(path, h5, "model/mean").reshape(-1)
    basis = _dataset(path, h5, "model/pcaBasis")
    variance = _dataset(path, h5, "model/pcaVariance").reshape(-1)
    if mean.shape != (3 * n,):
        raise DataFileError(path, f"model/mean has {mean.size} values, the representer has {n} "
                                  f"points (3N = {3 * n} expected)")
    if basis.ndim == 1 and variance.size == 1:
        basis = basis.reshape(-1, 1)
    if basis.ndim != 2 or basis.shape[0] != 3 * n:
        raise DataFileError(path, f"model/pcaBasis must be (3N, M) = ({3 * n}, M), got "
                                  f"{basis.shape}")
    if variance.shape != (basis.shape[1],):
        raise DataFileError(path, f"model/pcaVariance has {variance.size} values for "
                                  f"{basis.shape[1]} basis columns")
    for label, values in (("model/mean", mean), ("model/pcaBasis", basis),
                          ("model/pcaVariance", variance), ("representer/points", points)):
        if not np.all(np.isfinite(values)):
            raise DataFileError(path, f"{label} contains NaN or infinite values")
    if np.any(variance < 0):
        raise DataFileError(path, "model/pcaVariance has negative variances")
    if version == (0, 8):  # old files store U sqrt(lambda)
        scale = np.sqrt(variance)
        basis = basis / np.where(scale > 1e-12, scale, 1.0)
    gram = basis.T @ basis
    err = float(np.abs(gram - np.eye(len(gram))).max()) if len(gram) else 0.0
    if err > 1e-2:
        raise DataFileError(path, f"model/pcaBasis columns are not orthonormal (max |U'U - I| "
                                  f"= {err:.3g}); not a statismo {version[0]}.{version[1]} model")
    return mean, basis, variance


def _model_info(path: Path, h5, name: str, version: tuple[int, int], keep: np.ndarray) -> dict:
    """The model's ``info``: source format, PPCA noise variance, dropped components and the
    statismo modelinfo group."""
    info: dict = {"source_format": f"statismo {version[0]}.{version[1]}",
                  "statismo_representer": name}
    noise = _dataset(path, h5, "model/noiseVariance", required=False)
    if noise is not None and noise.size:
        nv = float(noise.reshape(-1)[0])
        if not np.isfinite(nv) or nv < 0:
            raise DataFileError(path, f"model/noiseVariance is {nv}, must be >= 0")
        info["noise_variance"] = nv
    if not keep.all():
        info["dropped_zero_variance_components"] = int((~keep).sum())
    modelinfo = _modelinfo(h5)
    if modelinfo:
        info["statismo_modelinfo"] = modelinfo
    return info


def _ssmstudio_group(path: Path, h5) -> dict | None:
    """Our extension group (exact factors and metadata), None when absent or unreadable."""
    if "ssmstudio" not in h5 or not isinstance(h5["ssmstudio"], _h5py().Group):
        return None
    group = h5["ssmstudio"]
    try:
        stored = {key: np.asarray(group[key][()], dtype=np.float64)
                  for key in ("mean", "factors", "coef_var", "world_transform")}
        stored["header"] = json.loads(_text(group.attrs.get("header", "{}")))
        stored["space"] = _text(group.attrs.get("space", "LPS"))
    except (KeyError, ValueError, TypeError, OSError):
        return None
    return stored


def _stored_model(stored: dict, faces, mean_file, basis, variance, to_world) -> ShapeModel | None:
    """The exact model kept by our writer, if it still describes the statismo datasets."""
    try:
        header = stored["header"] if isinstance(stored["header"], dict) else {}
        model = ShapeModel(mean=stored["mean"], factors=stored["factors"],
                           coef_var=stored["coef_var"], faces=faces,
                           world_transform=stored["world_transform"],
                           method=str(header.get("method", "statismo")),
                           params=dict(header.get("params", {})),
                           source_meshes=[str(m) for m in header.get("source_meshes", [])],
                           info=dict(header.get("info", {})))
    except (ValueError, TypeError, AttributeError):
        return None
    mean_ref, b_ref = _file_frame(model, to_world)
    tol = 1e-4 * max(1.0, float(np.abs(mean_file).max()))
    if mean_ref.shape != mean_file.shape or np.abs(mean_ref - mean_file).max() > tol:
        return None
    b_file = basis * np.sqrt(variance)
    if b_ref.shape != b_file.shape:
        return None
    # Same Gaussian: B_ref = B_file Q with Q orthogonal (Q = U^T B_ref / sqrt(lambda)).
    q = (basis.T @ b_ref) / np.sqrt(variance)[:, None]
    scale = max(float(np.abs(b_file).max()), 1e-12)
    if np.abs(b_file @ q - b_ref).max() > 1e-3 * scale or \
            np.abs(q.T @ q - np.eye(len(q))).max() > 1e-3:
        return None
    return model


def _file_frame(model: ShapeModel, to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean (3N,) and B = basis * sqrt(var) (3N, M) in the file's coordinates."""
    from_world = np.linalg.inv(to_world)
    total = from_world @ model.world_transform
    lin, shift = total[:3, :3], total[:3, 3]
    mean = (model.mean @ lin.T + shift).reshape(-1)
    factors = np.einsum("mnj,ij->mni", model.factors, lin)
    b = factors.reshape(model.n_factors, -1).T * np.sqrt(model.coef_var)[None, :]
    return mean, b


def _fixed(text: str) -> np.bytes_:
    """A fixed-length ASCII HDF5 string, as statismo's C++ writer stores them."""
    return np.bytes_(text.encode("ascii", "replace"))


def write_statismo(path: str | os.PathLike, model: ShapeModel, space: str = "LPS") -> None:
    """Write ``model`` as a statismo 0.9 triangle-mesh model (.h5) in ``space`` coordinates.

    The mean and basis are the model's world placement (``world_transform`` applied) in
    LPS (default, statismo's physical space) or RAS. Non-orthonormal factors are written by
    their covariance (module docstring); the model itself is kept in the ``ssmstudio``
    group. ``info["noise_variance"]`` becomes ``model/noiseVariance`` (0 when absent);
    ``info["statismo_modelinfo"]`` (from a file read earlier) is written back as modelinfo.
    """
    path = Path(path)
    space = space.upper()
    if space not in SPACES:
        raise DataFileError(path, f"unknown coordinate space '{space}' (LPS or RAS)")
    to_world = np.eye(4)
    if space == "LPS":
        to_world[:3, :3] = np.diag(_FLIP)
    mean, b = _file_frame(model, to_world)
    u, s, _ = np.linalg.svd(b, full_matrices=False) if model.n_factors else \
        (np.zeros((mean.size, 0)), np.zeros(0), None)
    order = np.argsort(-s, kind="stable")
    u, s = u[:, order], s[order]
    # a deterministic sign: the largest entry of each column positive
    signs = np.sign(u[np.abs(u).argmax(axis=0), np.arange(u.shape[1])]) if u.size else s
    u = u * np.where(signs == 0, 1.0, signs)[None, :]
    variance = s ** 2
    points = mean.reshape(-1, 3)
    h5py = _h5py()
    info = dict(model.info)
    modelinfo = info.pop("statismo_modelinfo", None)
    header = {"method": model.method, "params": model.params,
              "source_meshes": list(model.source_meshes), "info": info}
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as h5:
            grp = h5.create_group("model")
            grp.create_dataset("mean", data=mean.astype(np.float32))
            grp.create_dataset("pcaBasis", data=u.astype(np.float32))
            grp.create_dataset("pcaVariance", data=variance.astype(np.float32))
            grp.create_dataset("noiseVariance",
                               data=np.float32(model.info.get("noise_variance", 0.0) or 0.0))
            rep = h5.create_group("representer")
            rep.attrs["name"] = _fixed("itkStandardMeshRepresenter")
            rep.attrs["datasetType"] = _fixed("POLYGON_MESH")
            rep.attrs["version/majorVersion"] = _fixed("0")
            rep.attrs["version/minorVersion"] = _fixed("9")
            rep.create_dataset("points", data=points.T.astype(np.float32))
            rep.create_dataset("cells", data=model.faces.T.astype(np.int32))
            ver = h5.create_group("version")
            ver.create_dataset("majorVersion", data=np.int32(0))
            ver.create_dataset("minorVersion", data=np.int32(9))
            info_grp = h5.create_group("modelinfo")
            _write_modelinfo(info_grp, modelinfo or {})
            if "build-time" not in info_grp:
                info_grp.create_dataset("build-time", data=_fixed(time.strftime("%c")))
            ours = h5.create_group("ssmstudio")
            ours.attrs["header"] = json.dumps(header, default=_json_default)
            ours.attrs["space"] = space
            ours.create_dataset("mean", data=model.mean)
            ours.create_dataset("factors", data=model.factors)
            ours.create_dataset("coef_var", data=model.coef_var)
            ours.create_dataset("world_transform", data=model.world_transform)


def _write_modelinfo(group, values: dict) -> None:
    for key, value in values.items():
        if isinstance(value, dict):
            _write_modelinfo(group.require_group(key), value)
        elif isinstance(value, str):
            group.create_dataset(key, data=_fixed(value))
        else:
            try:
                group.create_dataset(key, data=np.asarray(value, dtype=np.float64))
            except (TypeError, ValueError):
                continue  # not numeric: skipped rather than pickled


def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return str(obj)


for _suffix in STATISMO_SUFFIXES:
    register(FileFormat(_suffix, "model", "statismo/Scalismo shape model (HDF5)",
                        read=read_statismo, write=write_statismo))
