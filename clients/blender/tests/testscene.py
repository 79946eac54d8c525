"""Test scenes built in code with bpy (Blender as a Python module), shared by the tests.

`cornell(lights)` builds a Cornell-like box in an empty Blender file: white floor, ceiling and
back wall, a red left and a green right wall (Principled BSDF with Specular IOR Level 0, i.e.
pure Lambertian, which the exporter writes as KHR_materials_specular factor 0), a glossy gold
metal box, a glass sphere, and the lights named in `lights`: "point" (50 W, radius 0), "sun"
(2 W/m^2, angle 0, through the open front) and "panel" (an emissive quad under the ceiling,
strength 8). A light left out is absent (the panel stays, black). The world is black, so the only
light is what the glTF export carries.
"""

import math
import os

import bmesh
import bpy

LIGHTS = ("point", "sun", "panel")


def worker_env():
    """The environment for pathfarm-worker processes: the library path its OIDN needs, which the
    test runner keeps out of this Python (bpy's SYCL runtime must not see it)."""
    env = dict(os.environ)
    if os.environ.get("PATHFARM_WORKER_LD_LIBRARY_PATH"):
        env["LD_LIBRARY_PATH"] = os.environ["PATHFARM_WORKER_LD_LIBRARY_PATH"]
    return env


def reset():
    """Empties the file (objects, meshes, materials, lights, cameras, worlds, images, actions),
    keeping the preferences and the enabled add-ons."""
    for collection in (bpy.data.objects, bpy.data.meshes, bpy.data.materials, bpy.data.lights):
        for block in list(collection):
            collection.remove(block)
    for collection in (bpy.data.cameras, bpy.data.worlds, bpy.data.images, bpy.data.actions):
        for block in list(collection):
            collection.remove(block)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end, scene.frame_current = 1, 1, 1


def principled(name, base, roughness=1.0, metallic=0.0, specular=0.0, transmission=0.0, emission=None):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    p = mat.node_tree.nodes["Principled BSDF"]
    p.inputs["Base Color"].default_value = (*base, 1.0)
    p.inputs["Roughness"].default_value = roughness
    p.inputs["Metallic"].default_value = metallic
    p.inputs["Specular IOR Level"].default_value = specular
    p.inputs["IOR"].default_value = 1.5
    p.inputs["Transmission Weight"].default_value = transmission
    if emission is not None:
        color, strength = emission
        p.inputs["Emission Color"].default_value = (*color, 1.0)
        p.inputs["Emission Strength"].default_value = strength
    return mat


def mesh_object(name, verts, faces, mat):
    me = bpy.data.meshes.new(name)
    me.from_pydata(verts, [], faces)
    me.update()
    me.materials.append(mat)
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob


def quad(name, corners, mat):
    """A quad; its front (counter-clockwise corners) faces the inside of the box."""
    return mesh_object(name, corners, [(0, 1, 2, 3)], mat)


def box(name, center, size, mat, rot_z=0.0):
    cx, cy, cz = center
    sx, sy, sz = (s / 2 for s in size)
    c, s = math.cos(rot_z), math.sin(rot_z)
    verts = []
    for z in (-sz, sz):
        for x, y in ((-sx, -sy), (sx, -sy), (sx, sy), (-sx, sy)):
            verts.append((cx + c * x - s * y, cy + s * x + c * y, cz + z))
    faces = [(3, 2, 1, 0), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    return mesh_object(name, verts, faces, mat)


def sphere(name, center, radius, mat):
    me = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=48, v_segments=24, radius=radius)
    bm.to_mesh(me)
    bm.free()
    for poly in me.polygons:
        poly.use_smooth = True
    me.materials.append(mat)
    ob = bpy.data.objects.new(name, me)
    ob.location = center
    bpy.context.scene.collection.objects.link(ob)
    return ob


def solid(mat, thickness):
    """Marks a transmissive material as a solid of `thickness` for Blender's glTF exporter (the
    "glTF Material Output" node group's Thickness), which then writes KHR_materials_volume: glTF
    transmission without it is a thin-walled sheet, while Cycles renders a solid."""
    group = bpy.data.node_groups.get("glTF Material Output")
    if group is None:
        group = bpy.data.node_groups.new("glTF Material Output", "ShaderNodeTree")
        group.interface.new_socket(name="Thickness", in_out="INPUT", socket_type="NodeSocketFloat")
    node = mat.node_tree.nodes.new("ShaderNodeGroup")
    node.node_tree = group
    node.inputs["Thickness"].default_value = thickness
    return mat


def cornell(lights=LIGHTS, panel_strength=8.0, size=(48, 48), default_walls=False):
    """Builds the box (see the module's doc) into the current, emptied file, rendering at
    `size` pixels (the exporter writes the camera's aspect ratio from it); returns the scene.
    `default_walls`: the walls keep the Principled BSDF's defaults (Specular IOR Level 0.5,
    roughness 0.5: a GGX dielectric coat over the diffuse base) instead of pure Lambertian."""
    unknown = set(lights) - set(LIGHTS)
    if unknown:
        raise ValueError(f"unknown lights {sorted(unknown)}")
    reset()
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = size
    scene.render.resolution_percentage = 100
    wall = {"roughness": 0.5, "specular": 0.5} if default_walls else {}
    white = principled("white", (0.8, 0.8, 0.8), **wall)
    red = principled("red", (0.6, 0.05, 0.05), **wall)
    green = principled("green", (0.1, 0.4, 0.08), **wall)
    metal = principled("gold metal", (0.9, 0.65, 0.3), roughness=0.3, metallic=1.0, specular=0.5)
    glass = solid(principled("glass", (1.0, 1.0, 1.0), roughness=0.0, specular=0.5, transmission=1.0), 0.8)
    strength = panel_strength if "panel" in lights else 0.0
    emitter = principled("panel", (0.0, 0.0, 0.0), emission=((1.0, 0.9, 0.75), strength))

    # The box: x in [-1, 1], y in [-1, 1] (open at y = -1, the camera's side), z in [0, 2].
    quad("floor", [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], white)
    quad("ceiling", [(-1, -1, 2), (-1, 1, 2), (1, 1, 2), (1, -1, 2)], white)
    quad("back", [(-1, 1, 0), (1, 1, 0), (1, 1, 2), (-1, 1, 2)], white)
    quad("left", [(-1, -1, 0), (-1, 1, 0), (-1, 1, 2), (-1, -1, 2)], red)
    quad("right", [(1, -1, 0), (1, -1, 2), (1, 1, 2), (1, 1, 0)], green)
    box("metal box", (0.4, 0.3, 0.45), (0.6, 0.6, 0.9), metal, rot_z=0.3)
    sphere("glass ball", (-0.45, -0.2, 0.4), 0.4, glass)
    quad("panel", [(-0.3, -0.3, 1.98), (-0.3, 0.3, 1.98), (0.3, 0.3, 1.98), (0.3, -0.3, 1.98)], emitter)

    if "point" in lights:
        data = bpy.data.lights.new("point", "POINT")
        data.energy = 50.0
        data.shadow_soft_size = 0.0
        ob = bpy.data.objects.new("point", data)
        ob.location = (-0.3, 0.2, 1.5)
        scene.collection.objects.link(ob)
    if "sun" in lights:
        data = bpy.data.lights.new("sun", "SUN")
        data.energy = 2.0
        data.angle = 0.0
        ob = bpy.data.objects.new("sun", data)
        # Light travels along the object's -Z: rotated 50 degrees about X it goes +y and down,
        # in through the open front onto the floor and the back wall.
        ob.rotation_euler = (math.radians(50.0), 0.0, math.radians(10.0))
        scene.collection.objects.link(ob)

    cam_data = bpy.data.cameras.new("camera")
    cam_data.angle = math.radians(40.0)
    cam = bpy.data.objects.new("camera", cam_data)
    cam.location = (0.0, -3.9, 1.0)
    cam.rotation_euler = (math.radians(90.0), 0.0, 0.0)
    scene.collection.objects.link(cam)
    scene.camera = cam

    world = bpy.data.worlds.new("black")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    scene.world = world
    return scene


def animate_point_light(frames):
    """Keyframes the point light's x position from -0.6 to 0.6 over `frames` (first, last)."""
    ob = bpy.data.objects["point"]
    first, last = frames
    ob.location.x = -0.6
    ob.keyframe_insert("location", index=0, frame=first)
    ob.location.x = 0.6
    ob.keyframe_insert("location", index=0, frame=last)
    scene = bpy.context.scene
    scene.frame_start, scene.frame_end = first, last


def export_glb(path, **options):
    """Blender's glTF exporter with the settings the add-on uses (`pathfarm/export.py`)."""
    from pathfarm import export  # the add-on's package (clients/blender on sys.path)

    return export.export_glb(path, **options)
