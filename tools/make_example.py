"""Regenerate the bundled example part (src/layerwatch/examples/part.{stl,gcode}).

The part is our own: a 40 x 40 x 4 mm plate with a hole, a thin-walled tube
(wall 0.8 mm) and a block on top, 10 mm tall, built with manifold3d and
sliced by Debian's PrusaSlicer centred at (110, 100) on a 220 x 220 mm bed.

Run:  .venv/bin/python tools/make_example.py   (needs `apt-get install prusa-slicer`)
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import manifold3d as m3d
import trimesh

OUT = Path(__file__).resolve().parents[1] / "src" / "layerwatch" / "examples"


def build_part() -> trimesh.Trimesh:
    base = m3d.Manifold.cube([40, 40, 4], True).translate([0, 0, 2])
    hole = m3d.Manifold.cylinder(10, 6, 6, 64).translate([8, 8, -1])
    tube = m3d.Manifold.cylinder(6, 7, 7, 96).translate([-9, -9, 4]) - m3d.Manifold.cylinder(
        8, 6.2, 6.2, 96
    ).translate([-9, -9, 3])
    block = m3d.Manifold.cube([12, 20, 6], False).translate([4, -16, 4])
    mesh = ((base - hole) + tube + block).to_mesh()
    return trimesh.Trimesh(mesh.vert_properties[:, :3], mesh.tri_verts)


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    stl = OUT / "part.stl"
    build_part().export(stl)
    subprocess.run(
        [
            "prusa-slicer", "--export-gcode", str(stl), "--center", "110,100",
            "--layer-height", "0.3", "--first-layer-height", "0.3", "--fill-density", "20%",
            "--perimeters", "2", "--skirts", "1", "--nozzle-diameter", "0.4",
            "--filament-diameter", "1.75", "--bed-shape", "0x0,220x0,220x220,0x220",
            "--gcode-flavor", "marlin2", "-o", str(OUT / "part.gcode"),
        ],
        check=True,
    )


if __name__ == "__main__":
    main()
