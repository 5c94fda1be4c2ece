"""Layer detection: each slicer's tag style, Z fallback with Z-hops, spiral binning."""

from __future__ import annotations

import math

import numpy as np
import pytest

from layerwatch.gcode import read_toolpath
from layerwatch.gcode.toolpath import FEATURES


def square(z: float, e0: float, hop: float = 0.0) -> tuple[str, float]:
    lines = []
    if hop:
        lines += [f"G1 Z{z + hop:.3f}", "G1 X0 Y0", f"G1 Z{z:.3f}"]
    else:
        lines += [f"G1 Z{z:.3f}", "G1 X0 Y0"]
    for x, y in [(10, 0), (10, 10), (0, 10), (0, 0)]:
        e0 += 0.5
        lines.append(f"G1 X{x} Y{y} E{e0:.4f}")
    return "\n".join(lines) + "\n", e0


def part(n: int, tag, hop: float = 0.0) -> bytes:
    out, e = ["G90\nM82\n"], 0.0
    for k in range(n):
        z = 0.2 * (k + 1)
        if tag:
            out.append(tag(k, z))
        body, e = square(z, e, hop)
        out.append(body)
    return "".join(out).encode()


STYLES = {
    "prusaslicer": lambda k, z: f";LAYER_CHANGE\n;Z:{z:.3f}\n;HEIGHT:0.2\n",
    "cura": lambda k, z: f";LAYER:{k}\n;TYPE:WALL-OUTER\n",
    "simplify3d": lambda k, z: f"; layer {k + 1}, Z = {z:.3f}\n; feature outer perimeter\n",
    "bambu": lambda k, z: f"; CHANGE_LAYER\n; Z_HEIGHT: {z:.3f}\n; FEATURE: Outer wall\n",
    "kisslicer": lambda k, z: f"; BEGIN_LAYER_OBJECT z={z:.3f} z_thickness=0.2\n; 'Perimeter Path', 1.0 [feed mm/s]\n",
    "flashprint": lambda k, z: f";layer:{z:.3f}\n",
}


@pytest.mark.parametrize("style", list(STYLES))
def test_tag_styles(style):
    tp = read_toolpath(part(7, STYLES[style]))
    assert tp.detection == f"tags:{style}"
    assert tp.n_layers == 7
    np.testing.assert_allclose([lay.z for lay in tp.layers], 0.2 * np.arange(1, 8), atol=1e-9)
    np.testing.assert_allclose([lay.height for lay in tp.layers], 0.2, atol=1e-9)
    if style not in ("flashprint", "prusaslicer"):
        assert FEATURES[int(tp.feature[0])] == "external_perimeter"


def test_z_fallback_ignores_z_hops():
    tp = read_toolpath(part(6, None, hop=0.6))
    assert tp.detection == "z"
    assert tp.n_layers == 6
    np.testing.assert_allclose([lay.extrusion_mm for lay in tp.layers], 2.0)
    np.testing.assert_allclose([lay.z for lay in tp.layers], 0.2 * np.arange(1, 7), atol=1e-9)


def test_spiral_binned_on_layer_height():
    lines = ["G90\nM83\n; layer_height = 0.25\nG1 X10 Y0 Z0.25\n"]
    for k in range(1, 40 * 8 + 1):  # 8 turns of 40 steps, rising 0.25 per turn
        a = 2 * math.pi * k / 40
        z = 0.25 + 0.25 * k / 40
        lines.append(f"G1 X{10 * math.cos(a):.4f} Y{10 * math.sin(a):.4f} Z{z:.5f} E0.05\n")
    tp = read_toolpath("".join(lines).encode())
    assert tp.detection == "spiral"
    assert tp.n_layers == 8
    np.testing.assert_allclose([lay.z for lay in tp.layers], 0.25 + 0.25 * np.arange(1, 9), atol=1e-6)
    assert all(lay.n_segments == 40 for lay in tp.layers)


def test_purge_before_first_tag_joins_layer_zero():
    data = b"G1 Z0.2\nG1 X0 Y-5 E2\nG92 E0\n" + part(3, STYLES["cura"])
    tp = read_toolpath(data)
    assert tp.n_layers == 3 and tp.layers[0].n_segments == 5


def test_bead_width_from_e():
    # 0.45 mm wide, 0.2 mm high rounded-rectangle bead, 10 mm long
    w, h, d, length = 0.45, 0.2, 1.75, 10.0
    e = length * ((w - h) * h + math.pi * (h / 2) ** 2) / (math.pi * d * d / 4)
    body = f";LAYER:0\nG1 Z0.2\nG1 X0 Y0\nG1 X10 Y0 E{e:.6f}\n;LAYER:1\nG1 Z0.4\nG1 X0 Y0 E{2 * e:.6f}\n"
    tp = read_toolpath(body.encode())
    np.testing.assert_allclose(tp.width, w, rtol=1e-4)


def test_z_fallback_purge_line_above_first_layer_joins_it():
    purge = b"G1 Z0.3\nG1 X0 Y-5\nG1 X50 Y-5 E5\nG92 E0\n"
    tp = read_toolpath(purge + part(5, None))
    assert tp.detection == "z" and tp.n_layers == 5
    assert tp.layers[0].z == pytest.approx(0.2) and tp.layers[0].n_segments == 5


def interleaved(steps=(0.26, 0.28), n=8) -> bytes:
    """Two objects side by side with their own layer heights, printed in order of Z (as KISSlicer does)."""
    zs = sorted((round(h * (k + 1), 3), o) for o, h in enumerate(steps) for k in range(n))
    out, e = ["G90\nM82\n"], 0.0
    for z, o in zs:
        x0 = 40.0 * o
        out.append(f"G1 Z{z:.3f}\nG1 X{x0} Y0\n")
        for x, y in [(x0 + 10, 0), (x0 + 10, 10), (x0, 10), (x0, 0)]:
            e += 0.4
            out.append(f"G1 X{x} Y{y} E{e:.4f}\n")
    return "".join(out).encode()


def test_interleaved_objects_get_their_own_layer_thickness():
    tp = read_toolpath(interleaved())
    assert tp.n_layers == 16
    for lay in tp.layers:
        x0 = tp.start[lay.seg_start][0]
        own = 0.26 if x0 < 20 else 0.28  # the step from the same object's previous layer, not 0.02
        assert lay.height == pytest.approx(own, abs=1e-3)
    w = tp.width
    assert w.max() < 1.5 * np.median(w)  # no bead inflated by a 0.02 mm "layer"


def test_kisslicer_per_object_layers_have_plausible_widths(shared_data):
    tp = read_toolpath(shared_data / "gcode" / "kisslicer-2.0.6.gcode")
    per_layer = [np.median(tp.width[tp.layer_slice(i)]) for i in range(tp.n_layers)]
    assert max(per_layer) < 0.6 and min(lay.height for lay in tp.layers) > 0.25
