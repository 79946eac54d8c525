"""pathfarm for Blender: submit the scene to a pathfarm render farm from Render Properties.

Preferences: the coordinator's URL, the client token, a CA file for https. The "pathfarm" panel
(Render Properties) holds the job's settings, taken from the scene when the panel first shows
(resolution, frame range) and editable. Submit exports the scene with Blender's glTF exporter
(.glb), uploads it, submits one job (a sequence for a frame range), follows progress in the status bar (HTTP in a
thread, a timer in Blender's main thread) and loads the finished EXRs as images (an image
sequence for a range). Errors from the coordinator are reported in words.
"""

import os
import tempfile
import time
import webbrowser

import bpy
from bpy.props import BoolProperty, EnumProperty, IntProperty, PointerProperty, StringProperty

from . import api, export, submission

INTEGRATORS = [
    ("path", "Path", "Path tracing with next-event estimation and MIS"),
    ("bdpt", "BDPT", "Bidirectional path tracing (perspective cameras)"),
    ("igi", "IGI", "Instant global illumination (virtual point lights)"),
    ("direct", "Direct", "Emission and direct lighting only"),
]

# The running submissions (Submission objects), newest last; the status bar shows the last one.
_submissions = []
# What the coordinator's job body accepts, per URL (from its OpenAPI document).
_offers = {}


def prefs(context=None):
    context = context or bpy.context
    return context.preferences.addons[__package__].preferences


def client_from_prefs(context=None):
    p = prefs(context)
    return api.Client(p.coordinator_url, p.client_token, p.ca_file or None)


class PathfarmPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    coordinator_url: StringProperty(
        name="Coordinator URL", default="http://127.0.0.1:8080", description="http:// or https:// address"
    )
    client_token: StringProperty(
        name="Client token", subtype="PASSWORD", description="The coordinator's client token (empty: no auth)"
    )
    ca_file: StringProperty(
        name="CA file", subtype="FILE_PATH", description="PEM certificates to trust for https (private CA)"
    )

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "coordinator_url")
        col.prop(self, "client_token")
        col.prop(self, "ca_file")
        col.operator(PATHFARM_OT_check.bl_idname, icon="LINKED")


class PathfarmSettings(bpy.types.PropertyGroup):
    initialized: BoolProperty(default=False, options={"HIDDEN"})
    integrator: EnumProperty(name="Integrator", items=INTEGRATORS, default="path")
    samples: IntProperty(name="Samples", default=64, min=1, soft_max=4096)
    max_depth: IntProperty(name="Max depth", default=8, min=0, max=1024, description="Path segments; 0 = no limit")
    width: IntProperty(name="Width", default=1920, min=1)
    height: IntProperty(name="Height", default=1080, min=1)
    frame_start: IntProperty(name="Start", default=1)
    frame_end: IntProperty(name="End", default=1)
    animation: BoolProperty(name="Animation", default=False, description="Render the frame range, not the current frame")
    priority: IntProperty(name="Priority", default=0, description="Higher runs first")
    denoise: BoolProperty(name="Denoise", default=False, description="Offered when the coordinator supports it")
    output_dir: StringProperty(
        name="Output", subtype="DIR_PATH", default="//pathfarm/", description="Where the finished EXRs are written"
    )
    last_job: IntProperty(name="Last job", default=-1, options={"HIDDEN"})


def sync_from_scene(scene):
    """Takes resolution and frame range from the scene's render settings."""
    s = scene.pathfarm
    r = scene.render
    s.width = max(1, r.resolution_x * r.resolution_percentage // 100)
    s.height = max(1, r.resolution_y * r.resolution_percentage // 100)
    s.frame_start = scene.frame_start
    s.frame_end = scene.frame_end
    s.initialized = True


def job_body(scene, offers):
    """The `POST /jobs` body (without scene id and frame) from the panel's settings."""
    s = scene.pathfarm
    integrator = {"type": s.integrator}
    if s.integrator in ("path", "bdpt"):
        integrator["max_depth"] = s.max_depth
    body = {
        "name": f"{bpy.path.display_name_from_filepath(bpy.data.filepath) or 'untitled'} ({scene.name})",
        "priority": s.priority,
        "width": s.width,
        "height": s.height,
        "spp": s.samples,
        "integrator": integrator,
        "fps": scene.render.fps / scene.render.fps_base,
    }
    if s.denoise and "denoise" in offers:
        body["denoise"] = True
    return body


def output_dir(scene):
    d = scene.pathfarm.output_dir
    if d.startswith("//") and not bpy.data.filepath:
        return os.path.join(tempfile.gettempdir(), "pathfarm", d[2:])
    return bpy.path.abspath(d)


def load_images(name, done):
    """Loads finished frames `[(frame, path)]` as Blender images: one image for one frame, an
    image sequence for a range. Returns the image."""
    done = sorted(done)
    first = done[0][1]
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)
    image = bpy.data.images.load(first, check_existing=False)
    image.name = name
    if len(done) > 1:
        image.source = "SEQUENCE"
    # Show it in the open Image Editors, a sequence over its frames.
    for window in getattr(bpy.context.window_manager, "windows", []):
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                space = area.spaces.active
                space.image = image
                if len(done) > 1:
                    space.image_user.frame_start = done[0][0]
                    space.image_user.frame_offset = done[0][0] - 1
                    space.image_user.frame_duration = len(done)
    return image


def status_text():
    if not _submissions:
        return ""
    s = _submissions[-1].snapshot()
    return "pathfarm: " + (s["error"] or s["status"])


def draw_status(self, context):
    text = status_text()
    if text:
        self.layout.label(text=text, icon="RENDER_ANIMATION")


def redraw_all():
    wm = bpy.context.window_manager
    for window in getattr(wm, "windows", []):
        for area in window.screen.areas:
            area.tag_redraw()


class PATHFARM_OT_check(bpy.types.Operator):
    """Ask the coordinator what its jobs accept (and check the URL and token)"""

    bl_idname = "pathfarm.check"
    bl_label = "Check connection"

    def execute(self, context):
        try:
            client = client_from_prefs(context)
            _offers[client.base] = client.check()
        except api.PathfarmError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, f"pathfarm: connected to {client.base}")
        return {"FINISHED"}


class PATHFARM_OT_sync(bpy.types.Operator):
    """Take resolution and frame range from the scene's render settings"""

    bl_idname = "pathfarm.sync"
    bl_label = "From scene"

    def execute(self, context):
        sync_from_scene(context.scene)
        return {"FINISHED"}


class PATHFARM_OT_submit(bpy.types.Operator):
    """Export the scene as glTF, upload it and render it on the pathfarm farm"""

    bl_idname = "pathfarm.submit"
    bl_label = "Submit to pathfarm"

    _timer = None
    _submission = None

    def execute(self, context):
        scene = context.scene
        if not scene.pathfarm.initialized:
            sync_from_scene(scene)
        s = scene.pathfarm
        if scene.camera is None:
            self.report({"ERROR"}, "pathfarm: the scene has no active camera")
            return {"CANCELLED"}
        try:
            client = client_from_prefs(context)
        except api.PathfarmError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        frames = list(range(s.frame_start, s.frame_end + 1)) if s.animation else [scene.frame_current]
        if not frames:
            self.report({"ERROR"}, f"pathfarm: empty frame range {s.frame_start}-{s.frame_end}")
            return {"CANCELLED"}
        # The exporter takes the camera's aspect ratio from the scene's resolution.
        r = scene.render
        saved = (r.resolution_x, r.resolution_y, r.resolution_percentage)
        r.resolution_x, r.resolution_y, r.resolution_percentage = s.width, s.height, 100
        try:
            with tempfile.TemporaryDirectory() as tmp:
                glb = os.path.join(tmp, "scene.glb")
                export.export_glb(glb, animation=s.animation)
                with open(glb, "rb") as f:
                    data = f.read()
        except Exception as e:  # noqa: BLE001 - the exporter's failure, in words
            self.report({"ERROR"}, f"pathfarm: the glTF export failed: {e}")
            return {"CANCELLED"}
        finally:
            r.resolution_x, r.resolution_y, r.resolution_percentage = saved
        self._name = bpy.path.clean_name(f"pathfarm_{scene.name}")
        self._submission = submission.Submission(
            client, data, job_body(scene, _offers.get(client.base, set())), frames, output_dir(scene), self._name
        ).start()
        _submissions.append(self._submission)
        if bpy.app.background or context.window is None:
            # No event loop to come back from (Blender as a module, command-line renders): wait.
            while not self._submission.snapshot()["finished"]:
                time.sleep(0.1)
            return self.finish(context)
        self._timer = context.window_manager.event_timer_add(0.25, window=context.window)
        context.window_manager.modal_handler_add(self)
        self.report({"INFO"}, "pathfarm: submitting")
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._submission.cancel()  # cancels the jobs; the thread then finishes with "cancelled"
        if event.type == "TIMER":
            redraw_all()
            if self._submission.snapshot()["finished"]:
                context.window_manager.event_timer_remove(self._timer)
                return self.finish(context)
        return {"PASS_THROUGH"}

    def finish(self, context):
        snap = self._submission.snapshot()
        if snap["jobs"]:
            context.scene.pathfarm.last_job = snap["jobs"][0]
        redraw_all()
        if snap["error"]:
            self.report({"ERROR"}, snap["error"])
            return {"CANCELLED"}
        image = load_images(self._name, snap["done"])
        self.report({"INFO"}, f"pathfarm: {len(snap['done'])} frame(s) loaded as image '{image.name}'")
        return {"FINISHED"}


class PATHFARM_OT_open_dashboard(bpy.types.Operator):
    """Open the coordinator's dashboard at the last submitted job"""

    bl_idname = "pathfarm.open_dashboard"
    bl_label = "Open dashboard"

    def execute(self, context):
        try:
            client = client_from_prefs(context)
        except api.PathfarmError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        job = context.scene.pathfarm.last_job
        webbrowser.open(client.dashboard_url(job if job >= 0 else None))
        return {"FINISHED"}


class RENDER_PT_pathfarm(bpy.types.Panel):
    bl_label = "pathfarm"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"

    def draw(self, context):
        layout = self.layout
        scene = context.scene
        s = scene.pathfarm
        layout.use_property_split = True
        col = layout.column()
        col.prop(s, "integrator")
        col.prop(s, "samples")
        if s.integrator in ("path", "bdpt"):
            col.prop(s, "max_depth")
        col.prop(s, "width")
        col.prop(s, "height")
        col.prop(s, "animation")
        sub = col.column(align=True)
        sub.enabled = s.animation
        sub.prop(s, "frame_start")
        sub.prop(s, "frame_end")
        col.operator(PATHFARM_OT_sync.bl_idname, icon="FILE_REFRESH")
        col.prop(s, "priority")
        try:
            offers = _offers.get(client_from_prefs(context).base, set())
        except api.PathfarmError:
            offers = set()
        if "denoise" in offers:
            col.prop(s, "denoise")
        col.prop(s, "output_dir")
        row = layout.row()
        row.scale_y = 1.4
        row.operator(PATHFARM_OT_submit.bl_idname, icon="RENDER_STILL")
        layout.operator(PATHFARM_OT_open_dashboard.bl_idname, icon="URL")
        text = status_text()
        if text:
            layout.label(text=text)


CLASSES = (
    PathfarmPreferences,
    PathfarmSettings,
    PATHFARM_OT_check,
    PATHFARM_OT_sync,
    PATHFARM_OT_submit,
    PATHFARM_OT_open_dashboard,
    RENDER_PT_pathfarm,
)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.pathfarm = PointerProperty(type=PathfarmSettings)
    bpy.types.STATUSBAR_HT_header.append(draw_status)


def unregister():
    bpy.types.STATUSBAR_HT_header.remove(draw_status)
    del bpy.types.Scene.pathfarm
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
