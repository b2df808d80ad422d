"""The data types the algorithms share: triangle meshes, volumes and point sets.

They are plain numpy containers with no file-format knowledge; :mod:`core.io` reads and
writes them (and re-exports them, so ``from core.io import TriMesh`` keeps working).
"""

from core.types.pointset import PointSet
from core.types.trimesh import TriMesh
from core.types.volume import Volume

__all__ = ["PointSet", "TriMesh", "Volume"]
