"""Scene builder that runs INSIDE Blender (``blender -b -P photoreal_scene.py -- job.json``).

Not imported by layerwatch itself. Reads a JSON job written by
:mod:`layerwatch.simulate.photoreal` and raw little-endian arrays (Debian's
Blender has no numpy), builds the simulator's scene and renders one 16-bit PNG
of linear radiance (no view transform: the simulator's sensor model develops it):

* the printed scene: quad meshes of the simulator's cells (one vertex a cell,
  bed mm, flat-shaded: the ground and the slabs printed over air), per-vertex
  albedo, specular weight and roughness of the cell's material (filament,
  strands, objects, bare bed);
* the bed: a plane textured with the bed's albedo (sheet texture, white dot
  markers), a dark plane beyond it;
* the lights of the simulated frame: a spot beside the camera (full inside
  30 deg, none beyond 60 deg), an overhead sun (the fill) and a uniform world
  (the ambient), at the strengths the job gives;
* the calibrated camera: a pinhole at the camera centre with the intrinsics of
  ``K`` (lens distortion is applied to the render afterwards, by the caller).

Units: one Blender unit is one millimetre.
"""

import array
import json
import math
import sys
from pathlib import Path

import bpy  # noqa: F401  (only available inside Blender)
from mathutils import Matrix

# the reference renderer's Blender script, beside this package: its mesh builder and array reader serve here too
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "render"))
from blender_scene import _mesh_object, _read  # noqa: E402


def _principled(name, base_attr=None, rgb=None, image=None, spec_attr=False, specular=0.1, roughness=0.6):
    """A Principled BSDF material: base colour from a point attribute, an image or a constant."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    pr = nt.nodes.new("ShaderNodeBsdfPrincipled")
    pr.inputs["Specular"].default_value = specular
    pr.inputs["Roughness"].default_value = roughness
    if base_attr:
        col = nt.nodes.new("ShaderNodeAttribute")
        col.attribute_name = base_attr
        nt.links.new(col.outputs["Color"], pr.inputs["Base Color"])
    elif image:
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = bpy.data.images.load(image)
        tex.image.colorspace_settings.name = "Non-Color"  # linear albedo values, not sRGB
        tex.interpolation = "Linear"
        tex.extension = "EXTEND"
        nt.links.new(tex.outputs["Color"], pr.inputs["Base Color"])
    else:
        pr.inputs["Base Color"].default_value = (*rgb, 1.0)
    if spec_attr:
        ks = nt.nodes.new("ShaderNodeAttribute")
        ks.attribute_name = "specular"
        nt.links.new(ks.outputs["Fac"], pr.inputs["Specular"])
        ro = nt.nodes.new("ShaderNodeAttribute")
        ro.attribute_name = "roughness"
        nt.links.new(ro.outputs["Fac"], pr.inputs["Roughness"])
    nt.links.new(pr.outputs["BSDF"], out.inputs["Surface"])
    return mat


def _quad(x0, y0, x1, y1, z):
    return array.array("f", [x0, y0, z, x1, y0, z, x1, y1, z, x0, y1, z]), array.array("i", [0, 1, 2, 3]), array.array("i", [4])


def _scene_mesh(k, mesh, mat):
    """One of the printed scene's quad meshes, with per-vertex albedo, specular weight and roughness."""
    verts = _read(mesh["verts"], "f")
    loops = _read(mesh["quads"], "i")
    spec = _read(mesh["spec"], "f")
    me = _mesh_object(f"scene{k}", verts, loops, array.array("i", [4]) * (len(loops) // 4), mat).data
    col = me.color_attributes.new(name="albedo", type="FLOAT_COLOR", domain="POINT")
    col.data.foreach_set("color", _read(mesh["albedo"], "f"))
    ks = me.attributes.new(name="specular", type="FLOAT", domain="POINT")
    ks.data.foreach_set("value", spec[0::2])
    ro = me.attributes.new(name="roughness", type="FLOAT", domain="POINT")
    ro.data.foreach_set("value", spec[1::2])


def _camera(job):
    cam_data = bpy.data.cameras.new("cam")
    cam_data.type = "PERSP"
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.sensor_width = job["sensor_width_mm"]
    cam_data.lens = job["lens_mm"]
    cam_data.shift_x, cam_data.shift_y = job["shift"]
    cam_data.clip_start = 1.0
    cam_data.clip_end = 100_000.0
    cam = bpy.data.objects.new("cam", cam_data)
    cam.matrix_world = Matrix(job["camera_to_bed"])  # 4x4, rows
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam


def _lights(job):
    L = job["spot"]
    spot = bpy.data.lights.new("spot", type="SPOT")
    spot.energy = L["power_w"]
    spot.spot_size = math.radians(2 * L["outer_deg"])
    spot.spot_blend = L["blend"]
    spot.shadow_soft_size = L["radius_mm"]
    obj = bpy.data.objects.new("spot", spot)
    obj.matrix_world = Matrix(L["matrix"])  # 4x4, rows: the spot shines along its -z
    bpy.context.scene.collection.objects.link(obj)
    sun = bpy.data.lights.new("fill", type="SUN")
    sun.energy = job["fill_strength"]
    sun.angle = math.radians(60.0)  # an overhead area, not a point at infinity
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("fill", sun))
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bg.inputs["Strength"].default_value = job["ambient"]
    bpy.context.scene.world = world


def main(job_path):
    with open(job_path) as f:
        job = json.load(f)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if job["meshes"]:
        mat = _principled("scene", base_attr="albedo", spec_attr=True)
        for k, mesh in enumerate(job["meshes"]):
            _scene_mesh(k, mesh, mat)
    x0, y0, x1, y1 = job["bed_box_mm"]
    verts, loops, sizes = _quad(x0, y0, x1, y1, -0.02)
    _mesh_object("bed", verts, loops, sizes, _principled("bed", image=job["bed_texture"], specular=job["bed_specular"],
                                                   roughness=job["bed_roughness"]),
          uvs=array.array("f", [0.0, 0.0, 1.0, 0.0, 1.0, 1.0, 0.0, 1.0]))
    far = 100.0 * max(x1 - x0, y1 - y0)
    verts, loops, sizes = _quad(x0 - far, y0 - far, x1 + far, y1 + far, -0.05)
    _mesh_object("floor", verts, loops, sizes, _principled("floor", rgb=job["background_rgb"], specular=0.1, roughness=0.8))
    _lights(job)
    _camera(job)
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y = job["resolution"]
    r.resolution_percentage = 100
    r.pixel_aspect_x, r.pixel_aspect_y = job.get("pixel_aspect", (1.0, 1.0))
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGB"
    r.image_settings.color_depth = "16"
    r.threads_mode = "FIXED" if job.get("threads") else "AUTO"
    if job.get("threads"):
        r.threads = int(job["threads"])
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(job["samples"])
    scene.cycles.seed = int(job.get("seed", 0))
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 4
    scene.display_settings.display_device = "None"  # linear values in the file: the caller's sensor develops them
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    r.filepath = job["output"]
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1])
