"""Checks of generated images."""
from __future__ import annotations

import struct

import numpy as np


def png_info(path):
    """(width, height) from the PNG header, and the pixel standard deviation."""
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path}: not a PNG"
    assert head[12:16] == b"IHDR"
    w, h = struct.unpack(">II", head[16:24])
    from PIL import Image

    with Image.open(path) as im:
        a = np.asarray(im.convert("L"), dtype=np.float64)
    return w, h, float(a.std())
