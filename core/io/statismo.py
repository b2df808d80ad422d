"""statismo / Scalismo shape models (HDF5 ``.h5``), read and written with h5py.

Layout (statismo 0.9+ as statismo and Scalismo write it; Luethi et al., "Statismo - a
framework for PCA based statistical models", Insight Journal 2012):

==================================  ============  ===========================================
path                                shape         meaning
==================================  ============  ===========================================
``model/mean``                      (3N,) f4      mean shape, x1 y1 z1 x2 y2 z2 ...
``model/pcaBasis``                  (3N, M) f4    basis U (orthonormal columns when a PCA
                                                  wrote it; see below)
``model/pcaVariance``               (M,) f4       variances lambda of the components
``model/noiseVariance``             () or (1,)    PPCA noise variance sigma^2 (optional)
``representer/points``              (3, N) f4     the reference mesh's points
``representer/cells``               (3, F) i4     its triangles
``representer`` attributes          ``name`` (itkStandardMeshRepresenter, vtkStandardMesh
                                    Representer, gravis::MeshShapeRepresenter), ``datasetType``
                                    (POLYGON_MESH): scalar strings (statismo) or 1-element
                                    string arrays (Scalismo)
``version/majorVersion|minor...``   () or (1,) i4 0.9 (0.8: basis stored as U sqrt(lambda))
``modelinfo/...``                   any           build time, scores, builder info (kept)
``catalog/NAME/modelPath|Type``     strings       several models in one file (scalismo-faces
                                                  morphable models: shape, color, expression)
==================================  ============  ===========================================

Mapping onto :class:`core.models.shape_model.ShapeModel` (exact): statismo (``StatisticalModel``:
``DrawSample = mean + U diag(sqrt(lambda)) a``) and Scalismo (``DiscreteLowRankGaussianProcess
.instance = basisMatrix * (sqrt(variance) * a) + mean``) both sample ``x = mean + U a`` with
``a ~ N(0, diag(lambda))`` and use the stored U as it is, without normalising it; ours is
``x = mean + sum_m a_m factor_m`` with ``a ~ N(0, diag(coef_var))``. So ``factors[m] =
U[:, m].reshape(N, 3)`` and ``coef_var = lambda``: the same Gaussian, covariance
``U diag(lambda) U^T``, whether or not U is orthonormal. A PCA model (statismo's
PCAModelBuilder) has an orthonormal U; a Gaussian-process model that Scalismo discretised
(``DiscreteLowRankGaussianProcess(domain, gp)``: the columns are the Nystrom eigenfunctions
evaluated at the points, normalised over the domain, not in R^3N) does not, e.g. Scalismo's
ASM test model (column norms 37 ~ sqrt(1400 points), |cos| between columns up to 0.1); how
far U is from orthonormal is kept in ``info["statismo_basis_orthonormality"]``. Version 0.8
files store U sqrt(lambda), divided out as statismo and Scalismo do.
``noiseVariance`` goes to ``info["noise_variance"]`` (the fit's variance floor,
:func:`core.reconstruction.fit_points`). Writing the other way, a model whose factors are
not orthonormal (LSF, SPLOCS, varimax, a GP model read here) is written by its covariance:
``B = factors diag(sqrt(coef_var))`` (3N x M) has the SVD ``B = U S V^T``, so ``pcaBasis = U``
and ``pcaVariance = S^2`` give the same Gaussian; its own factors are kept beside, in an
``ssmstudio`` group that other tools ignore, and are read back when they still match.

Files with several models (a ``catalog`` group, as scalismo-faces writes a morphable model)
are opened one model at a time as ``FILE#GROUP`` (scalismo-faces' URI fragment: ``face.h5
#shape`` or ``#/shape`` or the catalog entry ``#MorphableModel.shape``); colour and
expression models (``POLYGON_MESH_DATA_MODEL``: colours, or displacements added to a face)
are refused, with the shape model named.

Coordinates: the file holds world coordinates. statismo and Scalismo work in ITK's
physical space, LPS, so by default the mean and basis are read as LPS and the model's
``world_transform`` is diag(-1, -1, 1, 1) (LPS -> RAS); ``space="RAS"`` reads them as RAS.
Our writer writes LPS (and says so in ``ssmstudio`` attributes). Nothing in the file is
executed or unpickled: only numeric datasets and string attributes are read (the VTK
reference of statismo 0.8 files is parsed as mesh data), every object through
:class:`core.io.hdf5.H5Reader`, which never follows a link out of the file, never reads a
dataset stored in another file (external storage, virtual datasets) and checks declared
sizes before reading.
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from core.errors import DataFileError, require_file
from core.io.atomic import atomic_path
from core.io.hdf5 import H5Reader, integer_value, open_h5, text_value
from core.io.registry import FileFormat, register, split_member
from core.models.shape_model import ShapeModel

STATISMO_SUFFIXES = (".h5", ".hdf5")
MESH_REPRESENTERS = ("itkStandardMeshRepresenter", "vtkStandardMeshRepresenter",
                     "gravis::MeshShapeRepresenter")
_LEGACY_REPRESENTERS = ("vtkPolyDataRepresenter", "itkMeshRepresenter")
_FLIP = np.array([-1.0, -1.0, 1.0])
_MODELINFO_LIMIT = 200_000  # elements of one modelinfo dataset kept in the model's info
_MODELINFO_ENTRIES = 2_000  # modelinfo entries kept (a hostile file may hold millions)
_MODELINFO_DEPTH = 8
SPACES = ("LPS", "RAS")
SHAPE_MODEL_TYPE = "POLYGON_MESH_MODEL"


def _h5py():
    import h5py

    return h5py


def _at(root: str, name: str) -> str:
    return f"{root.rstrip('/')}/{name}"


def _numbers(h5: H5Reader, root: str, name: str) -> np.ndarray:
    return h5.read(_at(root, name), required_by="not a complete statismo model")


def _optional_numbers(h5: H5Reader, root: str, name: str) -> np.ndarray | None:
    return h5.read(_at(root, name))


def _version(h5: H5Reader, root: str, representer: str) -> tuple[int, int]:
    """(major, minor) from the model's ``version`` group, else the file's (Scalismo reads
    ``/version``; scalismo-faces writes one per sub-model and one at the root)."""
    for base in dict.fromkeys((root, "/")):
        major_raw, minor_raw = (h5.read(_at(base, f"version/{key}"), kinds="iufSUO")
                                for key in ("majorVersion", "minorVersion"))
        if major_raw is None or minor_raw is None:
            continue
        raw = (major_raw, minor_raw)
        major, minor = (integer_value(value) for value in raw)
        if major is None or minor is None:
            held = ", ".join(f"{value.dtype} {value.shape}" for value in raw)
            raise DataFileError(h5.path, f"version/majorVersion or minorVersion is not an "
                                         f"integer (holds {held})")
        return major, minor
    if representer in _LEGACY_REPRESENTERS:
        return 0, 8
    raise DataFileError(h5.path, "not a complete statismo model: no version/majorVersion and "
                                 "version/minorVersion")


def _legacy_reference(h5: H5Reader, root: str) -> tuple[np.ndarray, np.ndarray]:
    """statismo 0.8's reference mesh: a VTK file stored as bytes in representer/reference."""
    from core.io import load_mesh

    raw = h5.read(_at(root, "representer/reference"), kinds="iu",
                  required_by="not a complete statismo model")
    with tempfile.TemporaryDirectory() as tmp:
        ref = Path(tmp) / "reference.vtk"
        ref.write_bytes(raw.astype(np.uint8).tobytes())
        try:
            mesh = load_mesh(ref)
        except DataFileError as exc:
            raise DataFileError(h5.path, f"the embedded reference mesh is unreadable "
                                         f"({exc.problem})") from None
    return mesh.vertices, mesh.faces


def _modelinfo(h5: H5Reader, root: str) -> dict:
    """modelinfo/ as a JSON-friendly dict (strings, numbers, small arrays), nesting kept;
    every entry reached through the checked reader (no link leaves the file)."""
    out: dict = {}
    budget = [_MODELINFO_ENTRIES]
    h5py = _h5py()

    def visit(name: str, target: dict, depth: int) -> None:
        for key in h5.children(name):
            if budget[0] <= 0 or depth > _MODELINFO_DEPTH:
                return
            budget[0] -= 1
            child = f"{name}/{key}"
            node = h5.node(child)
            if isinstance(node, h5py.Group):
                visit(child, target.setdefault(key, {}), depth + 1)
                continue
            node = h5.dataset(child) if node is not None else None
            if node is None:
                continue
            with h5.reading(child):
                kind, size = node.dtype.kind, node.size
            if kind in "SUO":
                target[key] = text_value(h5.read(child, kinds="SUO"))
            elif kind in "iuf" and size <= _MODELINFO_LIMIT:
                target[key] = h5.read(child, required_by="modelinfo").tolist()  # present: above

    if h5.group(_at(root, "modelinfo")) is not None:
        visit(_at(root, "modelinfo"), out, 0)
    return out


def read_statismo(path: str | os.PathLike, space: str | None = None) -> ShapeModel:
    """Read a statismo/Scalismo triangle-mesh model (.h5) as a :class:`ShapeModel`.

    ``path`` may name one model of a file that holds several as ``FILE#GROUP`` (module
    docstring). ``space`` ("LPS" or "RAS") says which world coordinates the file holds; by
    default what our own writer recorded, else LPS (ITK's physical space, as statismo uses).

    Raises
    ------
    DataFileError
        Not HDF5, damaged, missing groups or datasets, mismatched shapes, non-finite values,
        a link or dataset that leaves the file, a declared size the file cannot hold, a
        catalog of several models without ``#GROUP``, or another representer (images,
        unstructured grids, tetrahedral meshes, point sets without cells, colour models).
    """
    file, member = split_member(path)
    file = require_file(file)
    with open_h5(file) as h5:
        root = _model_root(h5, member)
        try:
            return _read_open(h5, root, space)
        except MemoryError:
            raise DataFileError(file, "not enough memory to read this model") from None


def _catalog(h5: H5Reader) -> list[tuple[str, str, str]]:
    """(entry name, model type, group path) of each ``catalog`` entry (statismo/Scalismo's
    model catalog; scalismo-faces writes one for every morphable model)."""
    entries = []
    for name in h5.children("/catalog"):
        model_path = h5.read(f"/catalog/{name}/modelPath", kinds="SUO")
        model_type = h5.read(f"/catalog/{name}/modelType", kinds="SUO")
        group = "/" + "/".join(p for p in text_value(model_path).split("/") if p) \
            if model_path is not None else ""
        entries.append((name, text_value(model_type) if model_type is not None else "?", group))
    return entries


def _is_model(h5: H5Reader, root: str) -> bool:
    return h5.group(_at(root, "model")) is not None and \
        h5.group(_at(root, "representer")) is not None


def _member_name(group: str) -> str:
    return group.strip("/") or "/"


def _model_root(h5: H5Reader, member: str | None) -> str:
    """The group that holds the model to read: the file's root, or ``member``'s group."""
    catalog = _catalog(h5) if h5.group("/catalog") is not None else []
    shapes = [group for _, kind, group in catalog
              if kind == SHAPE_MODEL_TYPE and group and _is_model(h5, group)]
    listing = ", ".join(f"#{_member_name(group)} ({kind})" for _, kind, group in catalog
                        if group and _is_model(h5, group))
    if member is None:
        if _is_model(h5, "/"):
            return "/"
        if catalog:
            hint = (f"open its shape model as '{h5.path}#{_member_name(shapes[0])}'" if shapes
                    else "none of them is a triangle surface shape model")
            listing = listing or "no readable model"
            raise DataFileError(h5.path, f"a statismo model catalog ({listing}), not one model: "
                                         f"{hint}")
        raise DataFileError(h5.path, "not a statismo model (no 'model' and 'representer' groups)")
    by_entry = {name: group for name, _, group in catalog}
    group = by_entry.get(member) or "/" + "/".join(p for p in member.split("/") if p)
    if not _is_model(h5, group):
        raise DataFileError(h5.path, f"no model '#{member}' in the file (no '{group}/model' and "
                                     f"'{group}/representer' groups); "
                                     f"{'its models: ' + listing if listing else 'it has no catalog'}")
    kind = next((k for _, k, g in catalog if g == group), "")
    name = h5.text_attribute(_at(group, "representer"), "name")
    if kind.endswith("_DATA_MODEL") or "Color" in name or "Expression" in name:
        what = ("an expression model (displacements added to a face shape, not a shape)"
                if "xpression" in name + group else "a colour model (its mean holds colours, "
                                                    "not point positions)")
        hint = f"; its shape model is '#{_member_name(shapes[0])}'" if shapes else ""
        raise DataFileError(h5.path, f"'#{member}' is {what} (representer '{name or '?'}', "
                                     f"{kind or 'no catalog type'}){hint}")
    return group


def _read_open(h5: H5Reader, root: str, space: str | None) -> ShapeModel:
    """The model in group ``root`` (steps: representer, arrays, info, frame)."""
    path = h5.path
    rep = _at(root, "representer")
    name = h5.text_attribute(rep, "name")
    points, faces = _representer_mesh(h5, root, name)
    n = len(points)
    major, minor = _version(h5, root, name)
    if (major, minor) not in ((0, 8), (0, 9), (0, 10)) and major != 1:
        raise DataFileError(path, f"statismo format version {major}.{minor} is not supported")
    mean, basis, variance = _pca_arrays(h5, root, points, (major, minor))
    if faces.size == 0 or faces.min() < 0 or faces.max() >= n or \
            np.any(faces != np.rint(faces)):
        raise DataFileError(path, f"representer/cells must index the {n} points (0..{n - 1})")
    keep = variance > max(float(variance.max(initial=0.0)) * 1e-12, 0.0)
    info = _model_info(h5, root, name, (major, minor), keep, basis)
    stored = _ssmstudio_group(h5) if root == "/" else None
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


def _representer_mesh(h5: H5Reader, root: str, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) reference points and (F, 3) triangles of the representer (only triangle
    surfaces can be used: images, point sets, volume and line meshes are refused)."""
    path = h5.path
    kind = h5.text_attribute(_at(root, "representer"), "datasetType")
    if name in _LEGACY_REPRESENTERS:
        return _legacy_reference(h5, root)
    if kind != "POLYGON_MESH" and name not in MESH_REPRESENTERS:
        what = {"IMAGE": "an image (deformation) model", "POINT_SET": "a point-set model "
                "without cells", "VOLUME_MESH": "a volume (tetrahedral) mesh model",
                "LINE_MESH": "a line mesh model"}.get(kind, f"dataset type '{kind or '?'}'")
        raise DataFileError(path, f"{what} (representer '{name or '?'}'): only triangle "
                                  "surface models can be used")
    if kind and kind != "POLYGON_MESH":
        raise DataFileError(path, f"representer '{name}' holds dataset type '{kind}', not "
                                  "a triangle surface (POLYGON_MESH)")
    pts = _numbers(h5, root, "representer/points")
    cells = _optional_numbers(h5, root, "representer/cells")
    if cells is None:
        raise DataFileError(path, "a point-set model without cells (representer/cells): "
                                  "only triangle surface models can be used")
    if pts.ndim != 2 or pts.shape[0] != 3:
        raise DataFileError(path, f"representer/points must be (3, N), got {pts.shape}")
    if cells.ndim == 2 and cells.shape[0] == 4:
        raise DataFileError(path, f"a tetrahedral volume-mesh model (representer/cells holds "
                                  f"{cells.shape[1]} tetrahedra, 4 x {cells.shape[1]}): only "
                                  "triangle surface models can be used")
    if cells.ndim != 2 or cells.shape[0] != 3:
        raise DataFileError(path, f"representer/cells must be (3, F) triangles, got "
                                  f"{cells.shape}")
    return pts.T, cells.T


def _pca_arrays(h5: H5Reader, root: str, points: np.ndarray, version: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The checked (3N,) mean, (3N, M) basis U (as statismo and Scalismo use it: module
    docstring) and (M,) variances."""
    path = h5.path
    n = len(points)
    mean = _numbers(h5, root, "model/mean").reshape(-1)
    if mean.shape != (3 * n,):
        raise DataFileError(path, f"model/mean has {mean.size} values, the representer has {n} "
                                  f"points (3N = {3 * n} expected)")
    variance = _numbers(h5, root, "model/pcaVariance").reshape(-1)
    basis = _numbers(h5, root, "model/pcaBasis")
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
    if version == (0, 8):  # old files store U sqrt(lambda) (statismo's and Scalismo's reading)
        scale = np.sqrt(variance)
        basis = basis / np.where(scale > 1e-8, scale, 1.0)
    return mean, basis, variance


def _model_info(h5: H5Reader, root: str, name: str, version: tuple[int, int],
                keep: np.ndarray, basis: np.ndarray) -> dict:
    """The model's ``info``: source format, PPCA noise variance, dropped components, how
    far the basis is from orthonormal, and the statismo modelinfo group."""
    path = h5.path
    info: dict = {"source_format": f"statismo {version[0]}.{version[1]}",
                  "statismo_representer": name}
    if root != "/":
        info["statismo_submodel"] = root
    noise = _optional_numbers(h5, root, "model/noiseVariance")
    if noise is not None and noise.size:
        nv = float(noise.reshape(-1)[0])
        if not np.isfinite(nv) or nv < 0:
            raise DataFileError(path, f"model/noiseVariance is {nv}, must be >= 0")
        info["noise_variance"] = nv
    if not keep.all():
        info["dropped_zero_variance_components"] = int((~keep).sum())
    if basis.shape[1]:
        gram = basis.T @ basis
        info["statismo_basis_orthonormality"] = float(np.abs(gram - np.eye(len(gram))).max())
    modelinfo = _modelinfo(h5, root)
    if modelinfo:
        info["statismo_modelinfo"] = modelinfo
    return info


def _ssmstudio_group(h5: H5Reader) -> dict | None:
    """Our extension group (exact factors and metadata), None when absent or inconsistent
    (a link or dataset leaving the file is refused, as everywhere)."""
    if h5.group("/ssmstudio") is None:
        return None
    stored: dict = {}
    for key in ("mean", "factors", "coef_var", "world_transform"):
        value = h5.read(f"/ssmstudio/{key}")
        if value is None:
            return None
        stored[key] = value
    try:
        stored["header"] = json.loads(h5.text_attribute("/ssmstudio", "header", "{}"))
        stored["space"] = h5.text_attribute("/ssmstudio", "space", "LPS")
    except (ValueError, TypeError, RecursionError):
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
    info.pop("statismo_basis_orthonormality", None)  # of the file read; this one's is new
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
