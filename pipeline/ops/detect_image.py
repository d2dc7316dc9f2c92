"""Craters in any image a user brings (`just detect-image`): read, detect, score against labels,
write the table and overlays.

Images: PNG, JPEG, TIFF (8 or 16 bit, grey or colour: colour goes to luminance, ITU-R BT.601
weights as Pillow's "L"); larger than `MAX_PIXELS` is refused. Labels: the CSV of
`lro_nac_craters` (`ID,X,Y,W,H,C_X,CY`: a circle of centre (C_X, CY), diameter (W + H) / 2 px)
or YOLO text (`class xc yc w h` per line, normalised to the image's width and height when every
value is <= 1, else pixels), as a file or a folder holding `<image stem>.txt` / `.csv`. A label
and a detection match when the centres are within 0.25 x the label's diameter and the diameters
differ by less than 25 % (one-to-one, `render.match_detections`). Pixel (0, 0) is the corner of
the first pixel, u right, v down; the Sun's azimuth in the image is from +u towards +v (deg).
"""

from __future__ import annotations

import csv
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import polars as pl
from PIL import Image, ImageDraw, UnidentifiedImageError

from pipeline.core.vision.detectors import Detections, Detector
from pipeline.core.vision.sun_direction import SunEstimate, estimate_sun_direction, sun_from_rims
from pipeline.errors import PipelineError
from pipeline.io.tables import write_parquet
from pipeline.ops.render import match_detections

MAX_PIXELS = 400_000_000  # 20,000 x 20,000
OVERLAY_MAX_PX = 4096  # overlays are scaled down to this long side
# a float image is clipped to these percentiles of its pixels (%, each side): its outliers
FLOAT_CLIP_PERCENT = 0.01
SIZE_BINS_PX = (0.0, 10.0, 20.0, 50.0, np.inf)  # the first bin: what the targets leave out
DETECTIONS_SCHEMA: dict[str, type[pl.DataType]] = {
    "image": pl.String, "centre_u_px": pl.Float64, "centre_v_px": pl.Float64,
    "semi_major_px": pl.Float64, "semi_minor_px": pl.Float64, "angle_rad": pl.Float64,
    "confidence": pl.Float64}


class ImageInputError(PipelineError):
    """An image or label file that cannot be read as such."""


def read_image(path: Path) -> np.ndarray:
    """Grey levels (H, W) (uint8, uint16 or float32) of an image file; one-line errors for a
    missing, unreadable, empty or oversized file."""
    path = Path(path)
    if not path.is_file():
        what = ("a folder, not an image file" if path.is_dir() else
                "a link that leads nowhere (or round in a loop)" if path.is_symlink() else
                "no such file")
        raise ImageInputError(f"{path}: {what}")
    if path.stat().st_size == 0:
        raise ImageInputError(f"{path}: empty file (0 bytes)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            Image.MAX_IMAGE_PIXELS = MAX_PIXELS
            with Image.open(path) as im:
                w, h = im.size
                if w == 0 or h == 0:
                    raise ImageInputError(f"{path}: the image has no pixels ({w} x {h})")
                if w * h > MAX_PIXELS:
                    raise ImageInputError(f"{path}: {w} x {h} px is over {MAX_PIXELS:,} px")
                frames = getattr(im, "n_frames", 1)
                if frames > 1:  # a multi-page TIFF, an animated GIF or PNG
                    raise ImageInputError(f"{path}: {frames} images in one file; give one image "
                                          "per file")
                arr = _grey(im)
    except ImageInputError:
        raise
    except (UnidentifiedImageError, Image.DecompressionBombError) as exc:
        raise ImageInputError(f"{path}: not a readable PNG, JPEG or TIFF image ({exc})"
                              ) from None
    except (OSError, ValueError, SyntaxError) as exc:
        raise ImageInputError(f"{path}: cannot decode the image ({exc})") from None
    if arr.ndim != 2 or min(arr.shape) < 8:
        raise ImageInputError(f"{path}: {arr.shape[1] if arr.ndim > 1 else arr.size} x "
                              f"{arr.shape[0]} px is too small to hold a crater (8 px at least)")
    if arr.dtype.kind == "f":
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        if bad:
            raise ImageInputError(f"{path}: {bad:,} pixels are not finite (NaN or inf): mask or "
                                  "fill them first")
        # a float image's scale is its own: a hot pixel (1e30) must not set it
        lo, hi = np.percentile(arr[::max(1, arr.shape[0] // 1024), ::max(1, arr.shape[1] // 1024)],
                               [FLOAT_CLIP_PERCENT, 100.0 - FLOAT_CLIP_PERCENT])
        if not hi > lo:
            raise ImageInputError(f"{path}: the image is flat (all pixels {lo:g})")
        arr = np.clip(arr, lo, hi)
    return arr


def _grey(im: Image.Image) -> np.ndarray:
    """The image's grey levels: 8-bit as uint8, 16-bit as uint16, float as float32."""
    if im.mode in ("I;16", "I;16B", "I;16L", "I;16N"):
        return np.asarray(im).astype(np.uint16)
    if im.mode in ("I", "F"):
        return np.asarray(im).astype(np.float32)
    if im.mode in ("L", "P", "RGB", "RGBA", "LA", "CMYK", "YCbCr", "1"):
        return np.asarray(im.convert("L"))
    arr = np.asarray(im)
    return arr.mean(axis=-1).astype(np.float32) if arr.ndim == 3 else arr.astype(np.float32)


class Labels(NamedTuple):
    """Label centres (n, 2) px and diameters (n,) px of an image, and how many rows of the
    file lay outside it (left out)."""

    centre_px: np.ndarray
    diam_px: np.ndarray
    n_outside: int


def read_labels(path: Path, shape: tuple[int, int]) -> Labels:
    """The labels of a label file (module docstring) for an image of `shape` (H, W): a label
    whose crater (a disc) does not meet the image is left out (counted), a file most of whose
    labels lie outside, or a crater wider than twice the image, is refused (labels of another
    image)."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ImageInputError(f"{path}: cannot read the labels ({exc})") from None
    first = text.lstrip().splitlines()[0] if text.strip() else ""
    kind = "a crater label CSV (ID,X,Y,W,H,C_X,CY) nor YOLO text (class xc yc w h)"
    try:
        if "C_X" in first:
            rows = list(csv.DictReader(text.splitlines()))
            vals = np.array([[float(r["C_X"]), float(r["CY"]), float(r["W"]), float(r["H"])]
                             for r in rows]).reshape(-1, 4)
        else:
            lines = [ln for ln in text.splitlines() if ln.strip()]
            if any(len(ln.split()) < 5 for ln in lines):
                raise ValueError("a row with fewer than 5 fields")
            vals = np.array([[float(x) for x in ln.split()[1:5]] for ln in lines]).reshape(-1, 4)
    except (KeyError, ValueError, IndexError, TypeError) as exc:
        raise ImageInputError(f"{path}: not {kind}: {exc}") from None
    if not len(vals):
        raise ImageInputError(f"{path}: no labels in it (not {kind}?)")
    bad = ~(np.isfinite(vals).all(axis=1) & (vals[:, 2] > 0) & (vals[:, 3] > 0))
    if bad.any():
        raise ImageInputError(f"{path}: label row {int(np.flatnonzero(bad)[0]) + 1}: centre and "
                              f"size must be finite and the size > 0, got {vals[bad][0].tolist()}")
    h, w = shape
    if "C_X" not in first:  # YOLO: fractions of the image's width and height
        out = np.flatnonzero(~((vals >= 0) & (vals <= 1)).all(axis=1))
        if out.size:
            raise ImageInputError(f"{path}: label row {int(out[0]) + 1}: YOLO centre and size "
                                  f"are fractions of the image (0-1), got {vals[out[0]].tolist()}")
        vals = vals * np.array([w, h, w, h])
    r = 0.5 * (0.5 * vals[:, 2] + 0.5 * vals[:, 3])  # halves first: 1e308 + 1e308 overflows
    wide = np.flatnonzero(2 * r > 2 * max(h, w))
    if wide.size:
        i = int(wide[0])
        raise ImageInputError(f"{path}: label row {i + 1}: a crater of {2 * r[i]:.4g} px, wider "
                              f"than twice the {w} x {h} px image: labels of another image?")
    off = (vals[:, 0] < -r) | (vals[:, 0] > w + r) | (vals[:, 1] < -r) | (vals[:, 1] > h + r)
    if 2 * off.sum() > off.size:
        i = int(np.flatnonzero(off)[0])
        raise ImageInputError(f"{path}: {int(off.sum())} of {off.size} labels lie outside the "
                              f"{w} x {h} px image (row {i + 1}: ({vals[i, 0]:.4g}, "
                              f"{vals[i, 1]:.4g}) px): labels of another image?")
    return Labels(vals[~off, :2], 2 * r[~off], int(off.sum()))


def labels_for(labels: Path, image: Path) -> Path | None:
    """The label file of `image`: `labels` itself, or `<stem>.txt` / `.csv` in that folder."""
    if labels.is_dir():
        for ext in (".txt", ".csv"):
            p = labels / (image.stem + ext)
            if p.is_file():
                return p
        return None
    return labels


@dataclass(frozen=True)
class Scores:
    """Recall and precision by apparent diameter bin (`SIZE_BINS_PX`, lower edge in): per bin
    the labels, those found, the detections (by their own diameter) and those matched."""

    table: pl.DataFrame

    def counts(self, lo: float = 10.0) -> tuple[int, int, int, int]:
        """Labels, labels found, detections and detections matched in the bins from `lo` up."""
        t = self.table.filter(pl.col("diam_lo_px") >= lo)
        return (int(t["n_labels"].sum()), int(t["n_found"].sum()),
                int(t["n_detections"].sum()), int(t["n_matched"].sum()))

    def line(self, lo: float = 10.0) -> tuple[float, float]:
        """Pooled recall and precision of the bins from `lo` up."""
        n_lab, n_found, n_det, n_true = self.counts(lo)
        return (n_found / n_lab if n_lab else float("nan"),
                n_true / n_det if n_det else float("nan"))

    @staticmethod
    def pooled(parts: list[Scores]) -> Scores:
        """The scores of several images' together (their counts summed per bin)."""
        total = pl.concat([p.table for p in parts]).group_by(
            "diam_lo_px", "diam_hi_px", maintain_order=True).agg(
            pl.col("n_labels", "n_found", "n_detections", "n_matched").sum()).with_columns(
            recall=pl.col("n_found") / pl.col("n_labels"),
            precision=pl.col("n_matched") / pl.col("n_detections")).fill_nan(None)
        return Scores(total)


def score(det: Detections, label_centre: np.ndarray, label_diam: np.ndarray) -> Scores:
    """Match detections to labels (module docstring) and tabulate by size (`Scores`)."""
    det_d = 2.0 * np.sqrt(det.semi_major_px * det.semi_minor_px)
    d2t, t2d = match_detections(det.centre_px, det_d / 2, label_centre, label_diam / 2,
                                0.25, 0.25)
    edges = np.asarray(SIZE_BINS_PX)
    lb = np.searchsorted(edges, label_diam, side="right") - 1
    db = np.searchsorted(edges, det_d, side="right") - 1
    rows = []
    for k in range(edges.size - 1):
        lab, dd = lb == k, db == k
        rows.append({"diam_lo_px": edges[k], "diam_hi_px": edges[k + 1],
                     "n_labels": int(lab.sum()), "n_found": int(np.sum(lab & (t2d >= 0))),
                     "n_detections": int(dd.sum()), "n_matched": int(np.sum(dd & (d2t >= 0)))})
    t = pl.DataFrame(rows).with_columns(
        recall=pl.col("n_found") / pl.col("n_labels"),
        precision=pl.col("n_matched") / pl.col("n_detections")).fill_nan(None)
    return Scores(t)


def sun_direction_for(image: np.ndarray, azimuth_deg: float | None, det: Detections | None
                      ) -> tuple[np.ndarray | None, str]:
    """The Sun's image direction to use and a sentence saying where it comes from: given,
    estimated from the shading inside detected rims, or from the whole image."""
    if azimuth_deg is not None:
        a = np.radians(azimuth_deg)
        return np.array([np.cos(a), np.sin(a)]), f"Sun azimuth {azimuth_deg:g} deg (given)"
    est: SunEstimate
    if det is not None and len(det):
        est = sun_from_rims(image, det.centre_px, np.sqrt(det.semi_major_px * det.semi_minor_px))
        how = f"the shading inside {len(det)} detected rims"
    else:
        est = estimate_sun_direction(image)
        how = "the image's dark and bright crescents"
    if not np.isfinite(est.azimuth_rad):
        return None, f"Sun direction: not found from {how}"
    word = "estimated" if est.reliable else "unreliable estimate"
    return (est.direction if est.reliable else None,
            f"Sun azimuth {np.degrees(est.azimuth_rad):.0f} deg from +u towards +v ({word} from "
            f"{how}, strength {est.strength:.2f})")


def detect_image(detector: Detector, image: np.ndarray, sun_azimuth_deg: float | None
                 ) -> tuple[Detections, str]:
    """Detections in one image and the sentence on the Sun's direction (`sun_direction_for`):
    a detector that needs the Sun (classical) gets it first; the learned one finds the rims
    without it, and the Sun is then read from them."""
    if detector.name == "classical" or sun_azimuth_deg is not None:
        sun, said = sun_direction_for(image, sun_azimuth_deg, None)
        if sun is None:
            return Detections.empty(), said
        return detector.detect(image, sun), said
    det = detector.detect(image, None)
    _, said = sun_direction_for(image, None, det)
    return det, said


def table(name: str, det: Detections) -> pl.DataFrame:
    """The detections of one image as rows of `DETECTIONS_SCHEMA`."""
    return pl.DataFrame({
        "image": [name] * len(det), "centre_u_px": det.centre_px[:, 0],
        "centre_v_px": det.centre_px[:, 1], "semi_major_px": det.semi_major_px,
        "semi_minor_px": det.semi_minor_px, "angle_rad": det.angle_rad,
        "confidence": det.confidence}, schema=DETECTIONS_SCHEMA)


def _ellipse_points(c: np.ndarray, a: float, b: float, ang: float, k: float) -> list[float]:
    t = np.linspace(0, 2 * np.pi, 40)
    x = a * np.cos(t)
    y = b * np.sin(t)
    u = c[0] + x * np.cos(ang) - y * np.sin(ang)
    v = c[1] + x * np.sin(ang) + y * np.cos(ang)
    return np.stack([u * k, v * k], -1).ravel().tolist()


def overlay(path: Path, image: np.ndarray, det: Detections,
            labels: Labels | None = None) -> None:
    """A PNG of the image (stretched to 8 bits, scaled to at most OVERLAY_MAX_PX) with the
    detected rims (green) and, given labels, the labels found (blue) and missed (red)."""
    img = np.asarray(image, np.float32)
    lo, hi = np.percentile(img[::max(1, img.shape[0] // 512), ::max(1, img.shape[1] // 512)],
                           [0.5, 99.5])
    grey = np.clip((img - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    k = min(1.0, OVERLAY_MAX_PX / max(img.shape))
    pic = Image.fromarray(grey).convert("RGB")
    if k < 1.0:
        pic = pic.resize((max(1, round(img.shape[1] * k)), max(1, round(img.shape[0] * k))))
    draw = ImageDraw.Draw(pic)
    if labels is not None:
        lc, ld = labels.centre_px, labels.diam_px
        det_d = 2.0 * np.sqrt(det.semi_major_px * det.semi_minor_px)
        _, t2d = match_detections(det.centre_px, det_d / 2, lc, ld / 2, 0.25, 0.25)
        for c, d, m in zip(lc, ld, t2d, strict=True):
            draw.line(_ellipse_points(c, d / 2, d / 2, 0.0, k),
                      fill=(60, 120, 255) if m >= 0 else (255, 40, 40), width=1)
    for c, a, b, ang in zip(det.centre_px, det.semi_major_px, det.semi_minor_px, det.angle_rad,
                            strict=True):
        draw.line(_ellipse_points(c, a, b, ang, k), fill=(40, 255, 40), width=1)
    path.parent.mkdir(parents=True, exist_ok=True)
    pic.save(path)


def run(paths: list[Path], detector: Detector, out_dir: Path, sun_azimuth_deg: float | None = None,
        labels: Path | None = None) -> tuple[list[str], int]:
    """`just detect-image`: each image read, detected, scored against its labels when given,
    its overlay written (`<stem>_overlay.png`); then `detections.parquet` of all. Returns the
    lines to print and the number of inputs that could not be used (each said in one line).
    Every input is checked before any is detected, and the outputs are written together or not
    at all: a failed call leaves the folder's earlier outputs as they were."""
    import shutil
    import time

    lines = _check_inputs(paths, labels)
    if lines:
        return lines, len(lines)
    parts: list[pl.DataFrame] = []
    pooled: list[Scores] = []
    out_dir.mkdir(parents=True, exist_ok=True)
    staging = out_dir / f".detect-image-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        written: list[str] = []
        for path in paths:
            img = read_image(path)
            lab_file = labels_for(labels, path) if labels is not None else None
            lab = read_labels(lab_file, img.shape) if lab_file is not None else None
            if lab is not None and lab.n_outside:
                lines.append(f"{lab_file}: {lab.n_outside} labels outside the image left out")
            t0 = time.perf_counter()
            det, said = detect_image(detector, img, sun_azimuth_deg)
            ms = 1e3 * (time.perf_counter() - t0)
            parts.append(table(path.name, det))
            name = f"{path.stem}_overlay.png"
            overlay(staging / name, img, det, lab)
            written.append(name)
            lines.append(f"{path.name}: {img.shape[1]} x {img.shape[0]} px, {len(det)} craters "
                         f"({detector.name}, {ms:.0f} ms); {said}; overlay {out_dir / name}")
            if lab is not None:
                sc = score(det, lab.centre_px, lab.diam_px)
                pooled.append(sc)
                lines.extend(_score_lines(sc, f"  against {lab_file}"))
        if len(pooled) > 1:
            lines.extend(_score_lines(Scores.pooled(pooled), f"  pooled over {len(pooled)} images"))
        frame = pl.concat(parts) if parts else pl.DataFrame(schema=DETECTIONS_SCHEMA)
        write_parquet(frame, staging / "detections.parquet")
        for name in [*written, "detections.parquet"]:  # renames within one folder
            os.replace(staging / name, out_dir / name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    lines.append(f"wrote {out_dir / 'detections.parquet'} ({frame.height:,} craters in "
                 f"{len(parts)} images)")
    return lines, 0


def _check_inputs(paths: list[Path], labels: Path | None) -> list[str]:
    """One error line per input that cannot be used (nothing when all can): an unreadable
    image or label file, an image given twice or two of one name (the table's `image` column
    and the overlays are named by it), one label file for several images."""
    errors: list[str] = []
    seen: dict[str, Path] = {}
    for path in paths:
        try:
            path.name.encode("utf-8")
        except UnicodeEncodeError:
            shown = os.fsencode(path).decode("utf-8", "backslashreplace")
            errors.append(f"error: {shown}: the file name is not UTF-8 (the table's `image` "
                          "column holds it); rename it")
            return errors
        other = seen.get(path.name)
        if other is not None:
            same = other.resolve() == path.resolve()
            errors.append(f"error: {path}: {'given twice' if same else f'named as {other}'}; "
                          "the table and the overlays name the images by their file names")
        seen[path.name] = path
    if labels is not None and labels.is_file() and len(paths) > 1:
        errors.append(f"error: --labels {labels}: one label file for {len(paths)} images; give "
                      "a folder of <image stem>.txt or .csv files")
    for path in paths:
        try:
            img = read_image(path)
            lab_file = labels_for(labels, path) if labels is not None else None
            if labels is not None and lab_file is None:
                raise ImageInputError(f"{path}: no label file for it in {labels}")
            if lab_file is not None:
                read_labels(lab_file, img.shape)
        except ImageInputError as exc:
            errors.append(f"error: {exc}")
    return errors


def _score_lines(sc: Scores, head: str) -> list[str]:
    def pct(x: float | None) -> str:  # nothing to count: a dash, not nan
        return "  -  " if x is None or not np.isfinite(x) else f"{x:.3f}"

    rec, prec = sc.line(10.0)
    prec_all = sc.line(0.0)[1]
    out = [f"{head}: recall {pct(rec)}, precision {pct(prec)} (craters >= 10 px; centre within "
           f"0.25 D, diameter within 25 %); precision of every detection against every label "
           f"{pct(prec_all)}"]
    for r in sc.table.iter_rows(named=True):
        label = f"{r['diam_lo_px']:g}+" if np.isinf(r["diam_hi_px"]) else \
            f"{r['diam_lo_px']:g}-{r['diam_hi_px']:g}"

        out.append(f"    {label:>7} px: {r['n_labels']:5d} labels, recall {pct(r['recall'])}; "
                   f"{r['n_detections']:5d} detections, precision {pct(r['precision'])}")
    return out
