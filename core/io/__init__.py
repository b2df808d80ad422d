"""Every file SSM Studio reads or writes: volumes, meshes, point sets and shape models.

One package for I/O so that coordinates and errors are handled the same way everywhere.
One module per format family, each registering its readers and writers in the dispatch
table of :mod:`core.io.registry` (suffix -> reader/writer), as nibabel and trimesh do:

- :mod:`core.io.volumes` (dispatch) and :mod:`core.io.nifti`: NIfTI-1/2 (.nii, .nii.gz)
  through nibabel, kept with nibabel's best voxel->world affine (sform if set, else qform;
  RAS, mm), oblique affines included;
- :mod:`core.io.meshes` (dispatch, folder expansion, batch loading) and the mesh formats:
  :mod:`core.io.vtk_meshes` (.vtk .vtp .stl through VTK readers, their error output
  captured, never printed), :mod:`core.io.ply` and :mod:`core.io.obj` (numpy readers of our
  own), :mod:`core.io.gifti` (.gii through nibabel); always triangulated on load, as
  :class:`TriMesh`;
- :mod:`core.io.points`: CSV (header line, ``x,y,z`` or ``x,y,z,nx,ny,nz``, world RAS mm)
  and 3D Slicer markups JSON (.mrk.json; LPS or RAS on read, LPS on write as Slicer does);
- :mod:`core.io.models`: shape models, the versioned ``.npz`` format of :func:`save_model`;
  :mod:`core.io.statismo`: statismo/Scalismo ``.h5`` models (read and written by h5py);
- images beyond NIfTI: :mod:`core.io.itk_image` (NRRD, MetaImage through SimpleITK, exact
  LPS -> RAS), :mod:`core.io.nrrd` (NRRD header checks, our NRRD and Slicer ``.seg.nrrd``
  writer), :mod:`core.io.dicom` (DICOM series with their geometry checked);
- :mod:`core.io.atomic`: every save is atomic (a temporary file in the target folder, then
  renamed); :mod:`core.errors`: every load error is a :class:`DataFileError` naming the
  file and the problem.

Sessions are in :mod:`core.session.document`; the data types in :mod:`core.types` (re-exported here).
"""

from core.errors import DataFileError
from core.io.atomic import atomic_path, atomic_write_json, atomic_write_text
from core.io.meshes import MESH_SUFFIXES, expand_mesh_paths, load_mesh, load_meshes, save_mesh
from core.io.models import MODEL_FORMAT, MODEL_FORMAT_VERSION, load_model, save_model
from core.io.nifti import VOLUME_SUFFIXES
from core.io.points import POINT_SUFFIXES, load_points, save_points
from core.io.registry import FileFormat, file_suffix, lookup, register, suffixes
from core.io.statismo import read_statismo, write_statismo  # registers .h5 models
from core.io.volumes import load_volume, save_volume
from core.types import PointSet, TriMesh, Volume

__all__ = [
    "DataFileError", "FileFormat", "MESH_SUFFIXES", "MODEL_FORMAT", "MODEL_FORMAT_VERSION",
    "POINT_SUFFIXES", "PointSet", "TriMesh", "VOLUME_SUFFIXES", "Volume", "atomic_path",
    "atomic_write_json", "atomic_write_text", "expand_mesh_paths", "file_suffix", "load_mesh",
    "load_meshes", "load_model", "load_points", "load_volume", "lookup", "register",
    "read_statismo", "save_mesh", "save_model", "save_points", "save_volume", "suffixes",
    "write_statismo",
]
