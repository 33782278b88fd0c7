"""Names a job spec may use, kept importable without the pipeline (no numpy).

The strategy names are defined here, once: the preparation config and the localization
package import them. The renderer's object library owns the real object list; it is
repeated here so that the API validates a spec without importing geometry, and a test
checks that the two agree.
"""

from __future__ import annotations

#: Built-in obstacle meshes (renderer's object library).
BUILTIN_OBJECTS = ("person", "rock", "fallen_tree", "cow", "horse", "elephant")

#: Localization strategies a job may ask for (``auto`` picks one of the others).
STRATEGY_NAMES = ("ins", "odometry", "rails", "fused", "auto")
STRATEGIES = STRATEGY_NAMES

#: Archives accepted as assets: one mesh file and the files it references (an OBJ with
#: its .mtl and texture images), extracted by osdar_platform.archive_safety.
MESH_ARCHIVE_TYPES = ("zip", "tar.gz")

#: Mesh file types accepted for uploaded assets (loaded with an explicit type).
MESH_FILE_TYPES = ("glb", "gltf", "obj", "ply", "stl", "off", *MESH_ARCHIVE_TYPES)
