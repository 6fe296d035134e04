"""Pictures for people: a reconstructed surface as a colour-coded height map (PNG), a camera's
live frame (JPEG)."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["camera_jpeg", "height_map_png"]


def height_map_png(points: NDArray[np.floating], *, size_px: int = 512) -> bytes:
    """A PNG of ``points`` seen along Z: each pixel the mean Z of the points over it.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        x, y, z in mm (world coordinates).
    size_px : int, optional
        Length of the image's longer side in pixels; the other side keeps X and Y to scale.

    Returns
    -------
    bytes
        An 8-bit colour PNG: the 'turbo' colour map from the lowest Z (blue) to the highest
        (red); black where no point falls. Row 0 is the largest Y, so the image looks down Z
        with X to the right and Y up.
    """
    if size_px < 2:
        raise ValueError(f"size_px must be at least 2, got {size_px!r}")
    xyz = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    image: NDArray[np.uint8]
    if len(xyz) == 0:
        image = np.zeros((size_px, size_px, 3), np.uint8)
    else:
        low, high = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
        span = max(float((high - low).max()), 1e-6)
        mm_per_px = span / (size_px - 1)
        # Rounded, not floored: the longer side must come out at exactly size_px.
        width, height = (np.round((high - low) / mm_per_px).astype(int) + 1).tolist()
        col = np.clip(np.round((xyz[:, 0] - low[0]) / mm_per_px).astype(np.intp), 0, width - 1)
        row = height - 1 - np.clip(np.round((xyz[:, 1] - low[1]) / mm_per_px).astype(np.intp),
                                   0, height - 1)
        cell = row * width + col
        sums = np.bincount(cell, weights=xyz[:, 2], minlength=width * height)
        counts = np.bincount(cell, minlength=width * height)
        filled = counts > 0
        mean_z = np.zeros(width * height)
        mean_z[filled] = sums[filled] / counts[filled]
        z_low, z_high = mean_z[filled].min(), mean_z[filled].max()
        scaled = np.zeros(width * height, np.uint8)
        scaled[filled] = np.round(255 * (mean_z[filled] - z_low)
                                  / max(z_high - z_low, 1e-9)).astype(np.uint8)
        image = np.asarray(cv2.applyColorMap(scaled.reshape(height, width),
                                             cv2.COLORMAP_TURBO), dtype=np.uint8)
        image[~filled.reshape(height, width)] = 0
    ok, encoded = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - OpenCV encodes any 8-bit BGR image
        raise RuntimeError("OpenCV could not encode the height map")
    return encoded.tobytes()


def camera_jpeg(image: NDArray[np.integer], *, bit_depth: int = 8, max_side_px: int = 640,
                quality: int = 80) -> bytes:
    """A camera image as a grey JPEG for a screen: scaled to 8 bits and at most ``max_side_px``.

    Parameters
    ----------
    image : ndarray, shape (height, width)
        ``uint8``, or ``uint16`` holding ``bit_depth`` significant bits (unshifted).
    bit_depth : int, optional
        Significant bits per pixel (8 to 16).
    max_side_px : int, optional
        The longer side is shrunk (area averaging) to at most this many pixels.
    quality : int, optional
        JPEG quality, 1 to 100. A 640 × 480 fringe image is 30–60 kB at 80.

    Returns
    -------
    bytes
        A baseline single-channel JPEG.
    """
    pixels = np.asarray(image)
    if pixels.ndim != 2 or pixels.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"image must be a 2-D uint8 or uint16 array, got {pixels.dtype} "
                         f"with shape {pixels.shape}")
    if not 8 <= bit_depth <= 16:
        raise ValueError(f"bit_depth must be 8 to 16, got {bit_depth!r}")
    if max_side_px < 2:
        raise ValueError(f"max_side_px must be at least 2, got {max_side_px!r}")
    if not 1 <= quality <= 100:
        raise ValueError(f"quality must be 1 to 100, got {quality!r}")
    grey: NDArray[np.uint8] = (pixels if pixels.dtype == np.uint8
                               else (pixels >> (bit_depth - 8)).clip(0, 255).astype(np.uint8))
    height, width = grey.shape
    scale = max_side_px / max(height, width)
    if scale < 1:
        grey = np.asarray(cv2.resize(grey, (max(1, round(width * scale)),
                                            max(1, round(height * scale))),
                                     interpolation=cv2.INTER_AREA), dtype=np.uint8)
    ok, encoded = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:  # pragma: no cover - OpenCV encodes any 8-bit image
        raise RuntimeError("OpenCV could not encode the camera image")
    return encoded.tobytes()
