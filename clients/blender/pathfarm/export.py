"""The scene as pathfarm gets it: Blender's own glTF exporter, binary (.glb), with cameras,
punctual lights, animation and the material extensions it writes by itself
(KHR_materials_emissive_strength, _transmission, _ior, _volume, _specular).

Lights are written in glTF's photometric units (the exporter's default lighting mode
"Standard": W / 4 pi x 683 -> cd for point and spot lights, W/m^2 x 683 -> lux for suns); pathfarm
reads them back into Cycles' radiometric scale (README, "Units").
"""

import bpy


def export_glb(path, animation=True, selection_only=False):
    """Writes the current scene to `path` (.glb); returns `path`."""
    bpy.ops.export_scene.gltf(
        filepath=str(path),
        export_format="GLB",
        use_selection=selection_only,
        use_renderable=True,
        export_cameras=True,
        export_lights=True,
        export_import_convert_lighting_mode="SPEC",
        export_apply=True,
        export_yup=True,
        export_animations=animation,
        export_extras=True,
        check_existing=False,
    )
    return path
