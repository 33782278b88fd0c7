"""Names a job spec may use, kept importable without the pipeline (no numpy).

The renderer's object library and the localization package own the real lists; these
are repeated here so that the API validates a spec without importing geometry, and a
test checks that they agree where the other side exists.
"""

from __future__ import annotations

from worker.preparation.config import STRATEGY_NAMES

#: Built-in obstacle meshes (renderer's object library).
BUILTIN_OBJECTS = ("person", "rock", "fallen_tree", "cow", "horse", "elephant")

#: Localization strategies a job may ask for.
STRATEGIES = STRATEGY_NAMES

#: Mesh file types accepted for uploaded assets (loaded with an explicit type).
MESH_FILE_TYPES = ("glb", "gltf", "obj", "ply", "stl", "off")
