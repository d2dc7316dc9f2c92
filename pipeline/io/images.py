"""Rendered images as data: lossless PNG bytes (8-bit, or 16-bit greyscale above 8 bits), the
form `camera_images.parquet` keeps them in (one row per frame), so that images outlive the
recording and any detector can look at them again."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of a greyscale image (H, W): uint8 as 8-bit, uint16 as 16-bit (lossless)."""
    img = np.asarray(image)
    if img.dtype == np.uint8:
        pil = Image.fromarray(img)
    elif img.dtype == np.uint16:
        pil = Image.frombytes("I;16", (img.shape[1], img.shape[0]),
                              np.ascontiguousarray(img, dtype="<u2").tobytes())
    else:
        raise ValueError(f"an image of {img.dtype} cannot be stored: uint8 or uint16 only")
    buf = io.BytesIO()
    pil.save(buf, format="PNG", optimize=False, compress_level=6)
    return buf.getvalue()


def decode_png(data: bytes) -> np.ndarray:
    """The image (H, W) of `encode_png`'s bytes, in its own dtype (uint8 or uint16)."""
    with Image.open(io.BytesIO(data)) as pil:
        arr = np.asarray(pil)
    return arr.astype(np.uint16) if arr.dtype != np.uint8 else arr
