"""JPEG files decoded by libjpeg-turbo directly, when the optional ``simplejpeg`` package is installed.

A farm decodes every photo of every printer (a 1080p snapshot is ~0.3-0.5 MB of JPEG and 6 MB of
pixels). OpenCV's ``imdecode`` and ``simplejpeg`` run the same libjpeg-turbo decoder with the same
settings (accurate integer IDCT, smooth chroma upsampling, output straight to BGR), so they give the same
pixels; ``simplejpeg`` goes there with less around it (no decoder lookup, no copy into OpenCV's
buffers): ~6.7 against ~7.5 ms CPU for a 1080p 4:2:0 photo.

Only the files where the two are known to agree take this path (:func:`decode_jpeg` returns ``None``
for every other one, and the caller decodes with OpenCV): a baseline or progressive JPEG in YCbCr or
grey, without an Exif block (OpenCV turns a photo by its Exif orientation tag; ``simplejpeg`` does not),
that decodes without a libjpeg warning (a truncated or damaged file: OpenCV returns what it could
decode, and so does the fallback). ``tests/monitor/test_jpeg_decode.py`` compares the two, pixel for
pixel, over the chroma subsamplings, odd sizes, progressive and restart-marker files and grey files
(the farm benchmark's 1080p photos: the same pixels too, checked with ``benchmarks/farm_records.py``).

Install with ``pip install 'layerwatch[fast]'``; without it every file goes to OpenCV, as before.
"""

from __future__ import annotations

import numpy as np

try:  # optional: the `fast` extra
    import simplejpeg as _simplejpeg
except ImportError:  # pragma: no cover - depends on the environment
    _simplejpeg = None

__all__ = ["available", "decode_jpeg"]

#: colour spaces of a JPEG file that both decoders turn into BGR the same way
_SAME_COLOUR = ("YCbCr", "Gray")


def available() -> bool:
    """True when ``simplejpeg`` is installed (the fast path can be taken)."""
    return _simplejpeg is not None


def _has_exif(data: bytes) -> bool:
    """True when the JPEG's header segments (before the scan) hold an Exif block, or cannot be walked.

    Parameters
    ----------
    data : bytes
        A JPEG file (starts with the SOI marker ``FF D8``).
    """
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return True  # not a marker where one should be: leave the file to OpenCV
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0xDA:  # start of scan: no more header segments
            return False
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # markers without a length
            i += 2
            continue
        length = (data[i + 2] << 8) | data[i + 3]
        if marker == 0xE1 and data[i + 4:i + 10] == b"Exif\x00\x00":
            return True
        i += 2 + length
    return True


def decode_jpeg(data: bytes) -> np.ndarray | None:
    """A JPEG file decoded to BGR uint8, shape (H, W, 3), exactly as ``cv2.imdecode(..., IMREAD_COLOR)`` would.

    Parameters
    ----------
    data : bytes
        The file's bytes.

    Returns
    -------
    ndarray or None
        ``None`` when ``simplejpeg`` is not installed or the file is one this path leaves to OpenCV
        (not a JPEG, Exif, CMYK or YCCK colour, a libjpeg warning or error: module notes).
    """
    if _simplejpeg is None or not data.startswith(b"\xff\xd8") or _has_exif(data):
        return None
    try:
        if _simplejpeg.decode_jpeg_header(data)[2] not in _SAME_COLOUR:
            return None
        return np.asarray(_simplejpeg.decode_jpeg(data, colorspace="BGR", strict=True))
    except ValueError:  # damaged, truncated, 12-bit, arithmetic coded, ...: OpenCV decides
        return None
