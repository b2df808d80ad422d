"""The data types the algorithms share: triangle meshes, volumes and point sets.

They are plain numpy containers with no file-format knowledge; :mod:`core.io` reads and
writes them (and re-exports them, so ``from core.io import TriMesh`` keeps working).
"""

from core.types.pointset import PointSet
from core.types.trimesh import TriMesh
from core.types.volume import NiftiOrientation, Volume

__all__ = ["NiftiOrientation", "PointSet", "TriMesh", "Volume"]
