"""Footprint masks: polygon fill vs cv2.fillPoly, STL slices vs G-code beads, bad meshes."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh
from render_parts import square_part

from layerwatch.errors import RenderError
from layerwatch.geometry.topview import TopView
from layerwatch.render.mask import fill_polygons, gcode_mask, load_mesh, stl_mask

TV = TopView(6.67, 40.0, 40.0, (110.0, 100.0))


def _square(cx, cy, half, ccw=True):
    p = np.array([[cx - half, cy - half], [cx + half, cy - half], [cx + half, cy + half], [cx - half, cy + half]])
    return p if ccw else p[::-1]


def test_fill_polygons_vs_cv2_fillpoly():
    outer = np.array([[95.0, 88.0], [126.0, 91.5], [121.3, 117.2], [99.1, 112.0]])
    hole = _square(110.3, 101.7, 4.1, ccw=False)
    ours = fill_polygons([outer, hole], TV)
    ref = np.zeros(TV.shape, np.uint8)
    pts = [np.round(TV.to_px(p) * 256).astype(np.int32) for p in (outer, hole)]
    cv2.fillPoly(ref, pts, 1, cv2.LINE_8, shift=8)
    ref = ref.astype(bool)
    # cv2 includes the outline; every disagreement must lie on a polygon edge
    edge = np.zeros(TV.shape, np.uint8)
    cv2.polylines(edge, pts, True, 1, 3, cv2.LINE_8, shift=8)
    diff = ours ^ ref
    assert diff.sum() < 0.05 * ref.sum()
    assert not (diff & ~edge.astype(bool)).any()
    # the hole is empty, the ring is full
    u, v = TV.to_px(np.array([110.3, 101.7])).round().astype(int)
    assert not ours[v, u]
    # area (shoelace) from pixel count
    x, y = outer[:, 0], outer[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) - (8.2**2)
    assert ours.sum() / TV.px_per_mm**2 == pytest.approx(area, rel=0.01)


@pytest.fixture(scope="module")
def box_with_hole():
    """30 x 20 x 3 mm block with a 10 mm square hole, centred on (110, 100)."""
    outer = trimesh.creation.box((30.0, 20.0, 3.0))
    hole = trimesh.creation.box((10.0, 10.0, 5.0))
    import manifold3d

    def man(m):
        return manifold3d.Manifold(manifold3d.Mesh(
            vert_properties=m.vertices.astype(np.float32), tri_verts=m.faces.astype(np.uint32)))

    res = (man(outer) - man(hole)).to_mesh()
    mesh = trimesh.Trimesh(res.vert_properties[:, :3], res.tri_verts)
    mesh.apply_translation((110.0, 100.0, 1.5))
    return mesh


def test_stl_mask_area_and_hole(box_with_hole):
    m = stl_mask(box_with_hole, 1.0, TV)
    assert m.sum() / TV.px_per_mm**2 == pytest.approx(30 * 20 - 10 * 10, rel=0.01)
    u, v = TV.to_px(np.array([110.0, 100.0])).round().astype(int)
    assert not m[v, u]
    assert not stl_mask(box_with_hole, 5.0, TV).any()  # above the part


def test_gcode_mask_matches_stl_slice_on_synthetic_part():
    size, lh = 20.0, 0.3
    tp = square_part(3, center=(110.0, 100.0), size=size, layer_height=lh)
    mesh = trimesh.creation.box((size, size, 3 * lh))
    mesh.apply_translation((110.0, 100.0, 1.5 * lh))
    for i, layer in enumerate(tp.layers):
        g = gcode_mask(tp, i, TV)
        s = stl_mask(mesh, layer.z - layer.height / 2, TV)
        assert g.sum() == pytest.approx(s.sum(), rel=0.05)
        assert (g & s).sum() / (g | s).sum() > 0.95


def test_example_part_gcode_mask_vs_stl(example_gcode, example_stl):
    """Bundled part: G-code (centred X110 Y100) vs STL (centred at the origin)."""
    from layerwatch.gcode import read_toolpath

    tp = read_toolpath(example_gcode)
    mesh = load_mesh(example_stl)
    n = tp.n_layers
    for i in (1, 5, n // 2, n - 5, n - 1):
        layer = tp.layers[i]
        g = gcode_mask(tp, i, TV, solid=True)
        s = stl_mask(mesh, layer.z - layer.height / 2, TV, offset_mm=(110.0, 100.0, 0.0))
        assert s.sum() > 1000
        assert g.sum() == pytest.approx(s.sum(), rel=0.05), f"layer {i}"
        assert (g & s).sum() / (g | s).sum() > 0.95
    # solid (bottom/top) layers: the bead union alone matches too
    for i in (1, n - 1):
        layer = tp.layers[i]
        s = stl_mask(mesh, layer.z - layer.height / 2, TV, offset_mm=(110.0, 100.0, 0.0))
        assert gcode_mask(tp, i, TV).sum() == pytest.approx(s.sum(), rel=0.05)


def test_solid_mask_fills_sparse_infill_and_keeps_holes():
    tp = square_part(1, center=(110.0, 100.0), size=20.0, infill_spacing=3.0)
    beads = gcode_mask(tp, 0, TV)
    solid = gcode_mask(tp, 0, TV, solid=True)
    assert beads.sum() / TV.px_per_mm**2 < 0.6 * 400
    assert solid.sum() / TV.px_per_mm**2 == pytest.approx(400.0, rel=0.02)
    assert (solid | beads).sum() == solid.sum()
    # two external perimeters, one inside the other (a frame): even-odd keeps the hole
    from layerwatch.gcode.toolpath import Toolpath, feature_code

    a, b = _square(110, 100, 9.775), _square(110, 100, 5.225, ccw=True)
    start = np.concatenate([a, b])
    end = np.concatenate([np.roll(a, -1, 0), np.roll(b, -1, 0)])
    frame = Toolpath.from_segments(start, end, np.full(8, 0.3), 0.45,
                                   feature=np.full(8, feature_code("external_perimeter")))
    m = gcode_mask(frame, 0, TV, solid=True)
    assert m.sum() / TV.px_per_mm**2 == pytest.approx(20**2 - 10**2, rel=0.03)
    u, v = TV.to_px(np.array([110.0, 100.0])).round().astype(int)
    assert not m[v, u]


def test_non_watertight_repaired(tmp_path):
    mesh = trimesh.creation.box((10.0, 10.0, 4.0))
    mesh.update_faces(np.arange(len(mesh.faces)) != 0)  # drop one triangle
    assert not mesh.is_watertight
    path = tmp_path / "open.stl"
    mesh.export(path)
    tv = TopView(6.67, 20.0, 20.0, (0.0, 0.0))
    m = stl_mask(path, 1.0, tv)
    assert m.sum() / tv.px_per_mm**2 == pytest.approx(100.0, rel=0.02)


def test_unrepairable_and_missing_refused(tmp_path):
    sheet = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1]], [[0, 1, 2], [1, 3, 2]])
    with pytest.raises(RenderError, match="not watertight"):
        load_mesh(sheet)
    with pytest.raises(RenderError, match="not found"):
        stl_mask(tmp_path / "nope.stl", 1.0, TV)
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"solid x\nthis is not an stl\n")
    with pytest.raises(RenderError):
        stl_mask(bad, 1.0, TV)
