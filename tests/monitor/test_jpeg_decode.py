"""The fast JPEG path (simplejpeg) gives OpenCV's pixels, or leaves the file to OpenCV."""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest

from layerwatch.monitor import cameras, jpeg_decode

Image = pytest.importorskip("PIL.Image")

pytestmark = pytest.mark.skipif(not jpeg_decode.available(), reason="simplejpeg is not installed (the `fast` extra)")


def _photo(h: int, w: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = cv2.resize((rng.random((h // 8 + 1, w // 8 + 1, 3)) * 255).astype(np.uint8), (w, h),
                      interpolation=cv2.INTER_CUBIC)
    return np.clip(base.astype(int) + rng.integers(-20, 20, (h, w, 3)), 0, 255).astype(np.uint8)


def _pil(img: np.ndarray, **kw: object) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(img[..., ::-1])).save(buf, "JPEG", **kw)
    return buf.getvalue()


def _opencv(data: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def _encodings(img: np.ndarray) -> dict[str, bytes]:
    enc = {f"q{q}": cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, q])[1].tobytes() for q in (75, 95)}
    enc["progressive"] = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    enc["restarts"] = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_RST_INTERVAL, 4])[1].tobytes()
    for name, f in (("411", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411), ("440", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_440),
                    ("444", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444)):
        enc[f"sampling {name}"] = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_SAMPLING_FACTOR, f])[1].tobytes()
    for sub in (0, 1, 2):  # 4:4:4, 4:2:2, 4:2:0 from another encoder
        enc[f"pil subsampling {sub}"] = _pil(img, quality=85, subsampling=sub)
    enc["grey"] = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))[1].tobytes()
    return enc


@pytest.mark.parametrize("size", [(1080, 1920), (721, 1283), (17, 33)])
def test_same_pixels_as_opencv(size: tuple[int, int]) -> None:
    img = _photo(*size)
    for name, data in _encodings(img).items():
        fast = jpeg_decode.decode_jpeg(data)
        assert fast is not None, name
        ref = _opencv(data)
        assert fast.dtype == np.uint8 and fast.shape == ref.shape == (*size, 3), name
        assert np.array_equal(fast, ref), name
        assert np.array_equal(cameras.decode_image(data, "test"), ref), name


def test_files_left_to_opencv() -> None:
    img = _photo(120, 160)
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: OpenCV turns the photo, simplejpeg would not
    rotated = _pil(img, quality=85, exif=exif)
    cmyk = io.BytesIO()
    Image.fromarray(img[..., ::-1]).convert("CMYK").save(cmyk, "JPEG")
    whole = cv2.imencode(".jpg", img)[1].tobytes()
    png = cv2.imencode(".png", img)[1].tobytes()
    for name, data in (("exif", rotated), ("cmyk", cmyk.getvalue()), ("truncated", whole[: len(whole) * 2 // 3]),
                       ("png", png), ("garbage", b"\xff\xd8 not a jpeg at all")):
        assert jpeg_decode.decode_jpeg(data) is None, name
    assert cameras.decode_image(rotated, "test").shape == (160, 120, 3)  # OpenCV applied the orientation
    assert np.array_equal(cameras.decode_image(png, "test"), img)

