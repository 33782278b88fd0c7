"""Object assets: the procedural obstacle library, user meshes and levels of detail.

- :mod:`renderer.assets.sdf`: signed-distance primitives, smooth unions, marching cubes.
- :mod:`renderer.assets.obstacles`: person, rock, fallen tree, cow, horse, elephant
  (:func:`build_obstacle`, :data:`OBSTACLES`).
- :mod:`renderer.assets.user_mesh`: uploaded glTF/GLB, OBJ, PLY (:func:`load_user_mesh`).
- :mod:`renderer.assets.lod`: decimation and the face budget from the projected size.
"""

from renderer.assets.lod import choose_detail, simplify
from renderer.assets.obstacles import OBSTACLES, build_obstacle
from renderer.assets.user_mesh import MeshError, load_user_mesh

__all__ = [
    "OBSTACLES",
    "MeshError",
    "build_obstacle",
    "choose_detail",
    "load_user_mesh",
    "simplify",
]
