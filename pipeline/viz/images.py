"""Rendered images for people: JPEG encoding for the recording, and the report's contact sheet
(a few frames with the true rims and the detected ellipses drawn over them)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from pipeline.io.images import decode_png

JPEG_QUALITY = 85
_ELLIPSE = ("ellipse_u_px", "ellipse_v_px", "semi_major_px", "semi_minor_px", "ellipse_angle_rad")
# rim states drawn over the images (recording and contact sheet): RGB
MATCHED_COLOR = (60, 220, 90)  # detected, and a true rim
FALSE_COLOR = (240, 40, 220)  # detected, no true rim
MISSED_COLOR = (255, 170, 0)  # a true rim of 10 px or more not detected
TRUE_COLOR = (150, 150, 150)  # the true rims (thin)


def encode_jpeg(image: np.ndarray, size_px: int, bits: int) -> bytes:
    """JPEG bytes of a greyscale image (H, W) quantised to `bits` (scaled to 8 bits), resized
    so that its larger side is size_px."""
    img = np.asarray(image)
    if bits != 8:
        img = np.round(img.astype(np.float64) * (255.0 / (2**bits - 1))).astype(np.uint8)
    pil = Image.fromarray(img)
    scale = size_px / max(img.shape)
    if scale != 1.0:
        pil = pil.resize((round(img.shape[1] * scale), round(img.shape[0] * scale)),
                         Image.Resampling.LANCZOS)
    buf = io.BytesIO()
    pil.save(buf, format="JPEG", quality=JPEG_QUALITY)
    return buf.getvalue()


def _ellipse_xy(u: np.ndarray, v: np.ndarray, a: np.ndarray, b: np.ndarray, angle: np.ndarray
                ) -> list[np.ndarray]:
    """Closed polygons (n_i, 2) (px) of ellipses (`recording.ellipse_polygons`)."""
    from pipeline.viz.rerun.ellipses import ellipse_polygons, ellipse_segments

    points, offsets = ellipse_polygons(u, v, a, b, angle, ellipse_segments(a))
    return np.split(points, offsets[1:-1])


def decode_images(stored) -> list[np.ndarray]:
    """The images of a camera_images table (`pipeline.io.images` PNG bytes), in row order."""
    return [decode_png(b) for b in stored["png"].to_list()]


def contact_sheet(path: Path, frame: list[int], t_s: list[float], frames: list[np.ndarray],
                  detections, truth, title: str, bits: int, count: int) -> None:
    """A row of `count` rendered frames, evenly spaced over the images (quantised to `bits`),
    with the counted true rims (thin grey), the detections matched to one (green) or to none
    (magenta), and the counted true rims of 10 px or more that were missed (orange); the tables
    are the render stage's (`pixel_detections`, `rendered_craters`)."""
    pick = (sorted(set(np.linspace(0, len(frames) - 1, count).astype(int).tolist()))
            if frames else [])
    n = max(len(pick), 1)
    from matplotlib.figure import Figure  # lazy: only the render stage's sheet draws one

    fig = Figure(figsize=(4.2 * n, 4.6))
    axes = fig.subplots(1, n, squeeze=False)[0]
    for ax, i in zip(axes, pick, strict=False):
        image = frames[i]
        ax.imshow(image, cmap="gray", vmin=0, vmax=2**bits - 1)
        t = truth.filter(truth["frame"] == frame[i])
        d = detections.filter(detections["frame"] == frame[i])
        missed = (~t["detected"].to_numpy()) & (t["apparent_diam_px"].to_numpy() >= 10.0)
        for sel, color, lw in ((np.ones(t.height, bool), TRUE_COLOR, 0.4),
                               (missed, MISSED_COLOR, 0.9)):
            for xy in _ellipse_xy(*(t[f"true_{c}"].to_numpy()[sel] for c in _ELLIPSE)):
                ax.plot(xy[:, 0], xy[:, 1], color=np.array(color) / 255, lw=lw)
        real = d["crater_id"].to_numpy() >= 0
        for sel, color in ((real, MATCHED_COLOR), (~real, FALSE_COLOR)):
            for xy in _ellipse_xy(*(d[c].to_numpy()[sel] for c in _ELLIPSE)):
                ax.plot(xy[:, 0], xy[:, 1], color=np.array(color) / 255, lw=0.9)
        ax.set_xlim(0, image.shape[1])
        ax.set_ylim(image.shape[0], 0)
        ax.set_title(f"frame {frame[i]} (t = {t_s[i]:g} s): {int(real.sum())} matched, "
                     f"{int((~real).sum())} false", fontsize=8)
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    for ax in axes[len(pick):]:
        ax.set_axis_off()
    fig.suptitle(title + ": true rims grey, detected green, false magenta, missed orange",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
