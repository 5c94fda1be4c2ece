"""Type stub of the compiled G-code kernel (``_ckernel.c``; see :mod:`layerwatch.gcode.native`)."""

#: the slots and limits it was compiled with (compared with :mod:`layerwatch.gcode.kernel_abi`)
ABI: dict[str, int | float]
#: SHA-256 of the C source it was built from
SOURCE_KEY: str

def run(
    buf: bytes | bytearray | memoryview, probes: bytes | bytearray | memoryview, chord_tol: float, e_rel_init: bool, e_area_init: float, /
) -> tuple[bytearray, ...]: ...
