"""Object assets: the procedural obstacle library, user meshes and levels of detail.

- :mod:`renderer.assets.sdf`: signed-distance primitives, smooth unions, marching cubes.
- :mod:`renderer.assets.obstacles`: person (in :data:`PERSON_POSES`), rock, fallen tree,
  cow, horse, elephant (:func:`build_obstacle`, :data:`OBSTACLES`).
- :mod:`renderer.assets.textures`: tileable procedural detail textures (triplanar).
- :mod:`renderer.assets.user_mesh`: uploaded glTF/GLB, OBJ (+ MTL and textures in an
  archive), PLY, STL, OFF (:func:`load_user_mesh`).
- :mod:`renderer.assets.gltf_reader`: glTF scenes posed: skins, morph targets, animation.
- :mod:`renderer.assets.lod`: decimation and the face budget from the projected size.
"""

from renderer.assets.lod import choose_detail, simplify
from renderer.assets.obstacles import OBSTACLES, PERSON_POSES, build_obstacle
from renderer.assets.user_mesh import MeshError, load_user_mesh

__all__ = [
    "OBSTACLES",
    "PERSON_POSES",
    "MeshError",
    "build_obstacle",
    "choose_detail",
    "load_user_mesh",
    "simplify",
]
