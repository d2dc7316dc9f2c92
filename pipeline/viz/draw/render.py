"""The render stage's visuals: the images (JPEG) with their rims in render.rrd, the contact
sheet."""

from __future__ import annotations

from pipeline.viz import images
from pipeline.viz.draw import Drawing, table
from pipeline.viz.rerun import layout, rendered

CONTACT_SHEET_FRAMES = 4


def record_render(ctx: Drawing) -> None:
    """The rendered images (JPEG) with their rims in render.rrd, and the contact sheet."""
    cfg = ctx.cfg
    stored = table(ctx, "camera_images.parquet")
    detections = table(ctx, "pixel_detections.parquet")
    truth = table(ctx, "rendered_craters.parquet")
    per_image = table(ctx, "images.parquet")
    frames = images.decode_images(stored)
    jpegs = [images.encode_jpeg(img, cfg.render.recording_size_px, cfg.render.bits)
             for img in frames]
    with layout.recording(ctx.store.run_id, ctx.output("render.rrd")) as rec:
        rendered.log_images(rec, per_image, jpegs, cfg.detection.image_size_px,
                            cfg.render.recording_size_px, detections, truth)
    images.contact_sheet(ctx.output("contact_sheet.png"), stored["frame"].to_list(),
                         stored["t_s"].to_list(), frames, detections, truth,
                         f"Rendered frames with true and detected rims ({ctx.store.run_id})",
                         cfg.render.bits, CONTACT_SHEET_FRAMES)
