"""Build the optional ahead-of-time compiled G-code kernel (``layerwatch.gcode._ckernel``).

Everything else is declared in pyproject.toml. The extension is optional: where no C
compiler is found the build goes on without it and the reader uses its numba kernel.
``LW_SOURCE_KEY`` (the SHA-256 of the C source) is compiled in, so that a module built
from another version of the source is recognised and not used
(:mod:`layerwatch.gcode.native`).
"""

import hashlib
from pathlib import Path

from setuptools import Extension, setup

SOURCE = "src/layerwatch/gcode/_ckernel.c"
KEY = hashlib.sha256((Path(__file__).parent / SOURCE).read_bytes()).hexdigest()

setup(
    ext_modules=[
        Extension(
            "layerwatch.gcode._ckernel",
            [SOURCE],
            define_macros=[("LW_SOURCE_KEY", f'"{KEY}"')],
            # no fused multiply-add: the numba kernel rounds each product (identical outputs)
            extra_compile_args=["-O3", "-ffp-contract=off", "-fno-fast-math"],
            optional=True,
        )
    ]
)
