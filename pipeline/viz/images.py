"""Rendered images for people: JPEG encoding for the recording, and the report's contact sheet
(a few frames with the true rims and the detected ellipses drawn over them)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from PIL import Image

JPEG_QUALITY = 85
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
    from pipeline.viz.recording import ellipse_polygons, ellipse_segments

    points, offsets = ellipse_polygons(u, v, a, b, angle, ellipse_segments(a))
    return np.split(points, offsets[1:-1])


def contact_sheet(path: Path, frames: list, title: str, bits: int) -> None:
    """A row of rendered frames (frame, t_s, `pipeline.ops.render.FrameImage`; quantised to
    `bits`) with the true rims (thin grey), the detections matched to one (green) or to none
    (magenta), and the true rims of 10 px or more that were missed (orange)."""
    n = max(len(frames), 1)
    fig = Figure(figsize=(4.2 * n, 4.6))
    axes = fig.subplots(1, n, squeeze=False)[0]
    for ax, (frame, t_s, img) in zip(axes, frames, strict=False):
        ax.imshow(img.image, cmap="gray", vmin=0, vmax=2**bits - 1)
        t = img.truth
        for sel, color, lw in ((np.ones(t.row.size, bool), TRUE_COLOR, 0.4),
                               (t.counted & ~t.detected & (t.apparent_diam_px >= 10.0),
                                MISSED_COLOR, 0.9)):
            for xy in _ellipse_xy(t.centre_px[sel, 0], t.centre_px[sel, 1],
                                  t.semi_major_px[sel], t.semi_minor_px[sel], t.angle_rad[sel]):
                ax.plot(xy[:, 0], xy[:, 1], color=np.array(color) / 255, lw=lw)
        d = img.detections
        for sel, color in ((d.truth >= 0, MATCHED_COLOR), (d.truth < 0, FALSE_COLOR)):
            for xy in _ellipse_xy(d.centre_px[sel, 0], d.centre_px[sel, 1], d.semi_major_px[sel],
                                  d.semi_minor_px[sel], d.angle_rad[sel]):
                ax.plot(xy[:, 0], xy[:, 1], color=np.array(color) / 255, lw=0.9)
        ax.set_xlim(0, img.image.shape[1])
        ax.set_ylim(img.image.shape[0], 0)
        ax.set_title(f"frame {frame} (t = {t_s:g} s): {int((d.truth >= 0).sum())} matched, "
                     f"{int((d.truth < 0).sum())} false", fontsize=8)
        ax.set_xlabel("u (px)")
        ax.set_ylabel("v (px)")
    for ax in axes[len(frames):]:
        ax.set_axis_off()
    fig.suptitle(title + ": true rims grey, detected green, false magenta, missed orange",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
