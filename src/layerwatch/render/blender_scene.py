"""Scene builder that runs INSIDE Blender (``blender -b -P blender_scene.py -- job.json``).

Not imported by layerwatch itself. Reads a JSON job (written by
:mod:`layerwatch.render.blender`) and raw arrays of the bead mesh (Debian's Blender has no numpy), builds the
scene and renders one PNG:

* beads: one mesh of rounded prisms, procedural plastic material
  (Principled BSDF mixed with a Translucent BSDF through a noise texture, as
  in the paper),
* bed plane with the bed colour and white disc markers,
* an emissive ring light (torus) around the optical axis,
* a top-down orthographic camera covering the observed square.

References
----------
Petsiuk & Pearce (2022), Section 2.4 and Fig. 4 (Blender scene).
"""

import array
import json
import math
import sys

import bpy  # noqa: F401  (only available inside Blender)


def _material_plastic(rgb):
    mat = bpy.data.materials.new("plastic")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    pr = nt.nodes.new("ShaderNodeBsdfPrincipled")
    pr.inputs["Base Color"].default_value = (*rgb, 1.0)
    pr.inputs["Roughness"].default_value = 0.35
    tr = nt.nodes.new("ShaderNodeBsdfTranslucent")
    tr.inputs["Color"].default_value = (*rgb, 1.0)
    noise = nt.nodes.new("ShaderNodeTexNoise")
    noise.inputs["Scale"].default_value = 2.0
    ramp = nt.nodes.new("ShaderNodeMapRange")
    ramp.inputs["To Min"].default_value = 0.1
    ramp.inputs["To Max"].default_value = 0.35
    mix = nt.nodes.new("ShaderNodeMixShader")
    nt.links.new(noise.outputs["Fac"], ramp.inputs["Value"])
    nt.links.new(ramp.outputs["Result"], mix.inputs["Fac"])
    nt.links.new(pr.outputs["BSDF"], mix.inputs[1])
    nt.links.new(tr.outputs["BSDF"], mix.inputs[2])
    nt.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    return mat


def _material_simple(name, rgb, emission=0.0):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if emission > 0:
        sh = nt.nodes.new("ShaderNodeEmission")
        sh.inputs["Color"].default_value = (*rgb, 1.0)
        sh.inputs["Strength"].default_value = emission
        nt.links.new(sh.outputs["Emission"], out.inputs["Surface"])
    else:
        sh = nt.nodes.new("ShaderNodeBsdfDiffuse")
        sh.inputs["Color"].default_value = (*rgb, 1.0)
        nt.links.new(sh.outputs["BSDF"], out.inputs["Surface"])
    return mat


def _mesh_object(name, verts, faces_flat, face_sizes, mat, uvs=None):
    """Mesh from flat sequences: verts (3V floats), loops (L ints), sizes (F ints), optional uvs (2L floats).

    Also what :mod:`layerwatch.simulate.photoreal_scene` builds its meshes with.
    """
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(verts) // 3)
    me.vertices.foreach_set("co", verts)
    me.loops.add(len(faces_flat))
    me.loops.foreach_set("vertex_index", faces_flat)
    me.polygons.add(len(face_sizes))
    starts, acc = array.array("i"), 0
    for n in face_sizes:
        starts.append(acc)
        acc += n
    me.polygons.foreach_set("loop_start", starts)
    me.polygons.foreach_set("loop_total", face_sizes)
    if uvs is not None:
        me.uv_layers.new(name="uv").data.foreach_set("uv", uvs)
    me.update()
    me.validate()
    obj = bpy.data.objects.new(name, me)
    obj.data.materials.append(mat)
    bpy.context.scene.collection.objects.link(obj)
    return obj


def _read(path, code):
    """A raw little-endian array file (the caller writes ``<`` arrays) as an ``array.array`` of ``code``."""
    a = array.array(code)
    with open(path, "rb") as f:
        a.frombytes(f.read())
    if sys.byteorder != "little":
        a.byteswap()
    return a


def main(job_path):
    with open(job_path) as f:
        job = json.load(f)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    verts = _read(job["verts"], "f")
    if len(verts):
        loops, sizes = _read(job["loops"], "i"), _read(job["sizes"], "i")
        _mesh_object("beads", verts, loops, sizes, _material_plastic(job["material_rgb"]))
    cx, cy = job["center_mm"]
    w, h = job["size_mm"]
    # bed
    bed = _material_simple("bed", job["bed_rgb"])
    bw, bh = 2 * w, 2 * h
    verts = [(cx - bw, cy - bh, 0), (cx + bw, cy - bh, 0), (cx + bw, cy + bh, 0), (cx - bw, cy + bh, 0)]
    _mesh_object("bed", array.array("f", [c for v in verts for c in v]), array.array("i", [0, 1, 2, 3]), array.array("i", [4]), bed)
    white = _material_simple("marker", (0.95, 0.95, 0.95))
    for mx, my in job.get("markers_mm") or []:
        n = 24
        r = job["marker_diameter_mm"] / 2
        ring = [(mx + r * math.cos(2 * math.pi * k / n), my + r * math.sin(2 * math.pi * k / n), 0.01) for k in range(n)]
        flat = array.array("f", [c for v in ring for c in v])
        _mesh_object("marker", flat, array.array("i", range(n)), array.array("i", [n]), white)
    # ring light: emissive torus around the optical axis
    z_top = job["z_top"]
    bpy.ops.mesh.primitive_torus_add(
        major_radius=0.45 * max(w, h), minor_radius=0.03 * max(w, h),
        location=(cx, cy, z_top + 0.45 * max(w, h) * math.tan(math.radians(job["light_elevation_deg"]))),
    )
    torus = bpy.context.active_object
    torus.data.materials.append(_material_simple("ring", (1, 1, 1), emission=job["ring_strength"]))
    torus.visible_camera = False
    world = bpy.data.worlds.new("world")
    world.color = (0.02, 0.02, 0.02)
    scene.world = world
    # camera: orthographic, straight down, +Y up in the image
    cam_data = bpy.data.cameras.new("cam")
    cam_data.type = "ORTHO"
    cam_data.ortho_scale = max(w, h)
    cam_data.clip_start = 0.1
    cam_data.clip_end = 10_000
    cam = bpy.data.objects.new("cam", cam_data)
    cam.location = (cx, cy, z_top + 500.0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y = job["resolution"]
    r.resolution_percentage = 100
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGB"
    r.threads_mode = "FIXED"
    r.threads = int(job.get("threads", 2))
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(job["samples"])
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 4
    scene.view_settings.view_transform = "Standard"
    r.filepath = job["output"]
    bpy.ops.render.render(write_still=True)


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--") + 1])
