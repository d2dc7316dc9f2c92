"""`just detect-image` on what users bring: broken, empty, 16-bit, colour and huge images give
one clear line or a correct answer, never a traceback; the table and overlays as promised."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from PIL import Image

from pipeline import cli
from pipeline.core.sensors.scenes import SceneOptions, render_scene, scene_rng
from pipeline.ops import detect_image as di
from pipeline.ops.detectors import DEFAULT_MODEL

pytest.importorskip("onnxruntime")
needs_model = pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no trained model")


def _run(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, *args: str
         ) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", ["crater-nav", "detect-image", *args])
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def scene():
    return render_scene(scene_rng(99, 3), SceneOptions(size_px=256, n_ge10_px=(30.0, 40.0),
                                                       fresh_share=1.0))


def test_broken_and_empty_files_are_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    tiny = tmp_path / "tiny.png"
    Image.fromarray(np.zeros((3, 3), np.uint8)).save(tiny)
    (tmp_path / "folder.png").mkdir()
    (tmp_path / "loop.png").symlink_to(tmp_path / "loop.png")
    code, out, err = _run(monkeypatch, capsys, str(broken), str(empty), str(tiny),
                          str(tmp_path / "missing.tif"), str(tmp_path / "folder.png"),
                          str(tmp_path / "loop.png"), "--out", str(tmp_path / "o"),
                          "--detector", "classical")
    assert code == 1
    lines = err.strip().splitlines()
    assert len(lines) == 6 and all(line.startswith("error: ") for line in lines)
    assert "Traceback" not in out + err
    assert "broken.png: " in lines[0] and "empty file" in lines[1]
    assert "too small" in lines[2] and "no such file" in lines[3]
    assert "a folder" in lines[4] and "a link that leads nowhere" in lines[5]
    assert not (tmp_path / "o").exists()  # nothing written when an input cannot be used


def _crater_image(path: Path) -> Path:
    """A grey image with one dark-bright crater pair (the classical detector's crescents)."""
    img = np.full((128, 128), 100, np.uint8)
    yy, xx = np.mgrid[:128, :128]
    r = np.hypot(xx - 64, yy - 64)
    img[(r < 20) & (xx < 64)] = 40
    img[(r < 20) & (xx >= 64)] = 200
    Image.fromarray(img).save(path)
    return path


def test_a_failed_call_leaves_the_earlier_outputs(tmp_path: Path, monkeypatch, capsys) -> None:
    good = _crater_image(tmp_path / "good.png")
    out = tmp_path / "o"
    code, _, _ = _run(monkeypatch, capsys, str(good), "--out", str(out), "--detector",
                      "classical", "--sun-azimuth-deg", "0")
    assert code == 0
    before = (out / "detections.parquet").read_bytes()
    truncated = tmp_path / "cut.png"
    truncated.write_bytes(good.read_bytes()[:200])
    for args in ([str(truncated)], [str(good), str(truncated)]):
        code, _, err = _run(monkeypatch, capsys, *args, "--out", str(out), "--detector",
                            "classical")
        assert code == 1 and err.count("error: ") == 1 and "cut.png" in err
        assert (out / "detections.parquet").read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == ["detections.parquet", "good_overlay.png"]


def test_inputs_that_would_be_named_alike_or_scored_wrongly_are_refused(
        tmp_path: Path, monkeypatch, capsys) -> None:
    a = _crater_image(tmp_path / "img.png")
    (tmp_path / "b").mkdir()
    b = _crater_image(tmp_path / "b" / "img.png")
    labels = tmp_path / "l.txt"
    labels.write_text("0 0.5 0.5 0.3 0.3\n")
    nan_labels = tmp_path / "nan.txt"
    nan_labels.write_text("0 0.5 0.5 nan 0.3\n")
    yolo_out = tmp_path / "yolo_out.txt"
    yolo_out.write_text("0 0.5 0.5 0.1 0.1\n0 5.0 0.5 0.1 0.1\n")
    csv_out = tmp_path / "csv_out.csv"
    csv_out.write_text("ID,X,Y,W,H,C_X,CY\n1,10,10,7,7,13,13\n2,-5000,-5000,7,7,-4996,-4996\n"
                       "3,900,10,7,7,903,13\n")
    csv_huge = tmp_path / "csv_huge.csv"
    csv_huge.write_text("ID,X,Y,W,H,C_X,CY\n1,10,10,1e308,1e308,12,12\n")
    float_img = tmp_path / "f.tif"
    arr = np.full((64, 64), 0.1, np.float32)
    arr[0, 0] = np.nan
    Image.fromarray(arr).save(float_img)
    for args, said in (([str(a), str(b)], "named as"), ([str(a), str(a)], "given twice"),
                       ([str(a), str(b.with_name("c.png")), "--labels", str(labels)],
                        "one label file for 2 images"),
                       ([str(a), "--labels", str(nan_labels)], "label row 1"),
                       ([str(a), "--labels", str(yolo_out)], "label row 2: YOLO"),
                       ([str(a), "--labels", str(csv_out)], "2 of 3 labels lie outside"),
                       ([str(a), "--labels", str(csv_huge)], "label row 1: a crater"),
                       ([str(a), "--sun-azimuth-deg=1e300"], "within +-360"),
                       ([str(float_img)], "not finite"),
                       ([str(a), "--sun-azimuth-deg=nan"], "finite angle")):
        if "c.png" in " ".join(args):
            _crater_image(b.with_name("c.png"))
        code, out, err = _run(monkeypatch, capsys, *args, "--out", str(tmp_path / "o"),
                              "--detector", "classical")
        assert code == 1 and said in err and "Traceback" not in out + err, (args, err)
    assert not (tmp_path / "o").exists()


def test_a_file_of_several_images_is_refused(tmp_path: Path, monkeypatch, capsys) -> None:
    pages = tmp_path / "pages.tif"
    first = Image.fromarray(np.full((64, 64), 90, np.uint8))
    first.save(pages, save_all=True, append_images=[Image.fromarray(np.zeros((64, 64), np.uint8))])
    code, out, err = _run(monkeypatch, capsys, str(pages), "--out", str(tmp_path / "o"))
    assert code == 1 and "2 images in one file" in err and "Traceback" not in out + err


def test_out_is_never_a_runs_or_the_catalogues_folder(workdir, monkeypatch, capsys) -> None:
    img = _crater_image(workdir / "img.png")
    run = workdir / "runs" / "r"
    (run / ".stages").mkdir(parents=True)
    (workdir / "catalogue").mkdir(exist_ok=True)
    for out in (run / "detect", run, workdir / "catalogue" / "x"):
        code, _, err = _run(monkeypatch, capsys, str(img), "--out", str(out))
        assert code == 1 and "give another folder" in err
        assert not out.exists() or out == run


def test_blank_image_has_no_craters(tmp_path: Path, monkeypatch, capsys) -> None:
    blank = tmp_path / "blank.png"
    Image.fromarray(np.full((200, 300), 90, np.uint8)).save(blank)
    code, out, _ = _run(monkeypatch, capsys, str(blank), "--out", str(tmp_path / "o"),
                        "--detector", "classical")
    assert code == 0 and "0 craters" in out
    assert (tmp_path / "o" / "blank_overlay.png").is_file()


def test_16_bit_tiff_and_colour_jpeg_read_as_grey(tmp_path: Path, scene) -> None:
    img16 = scene.image.astype(np.uint16) * 250 + 300
    Image.fromarray(img16).save(tmp_path / "a.tif")
    got = di.read_image(tmp_path / "a.tif")
    assert got.dtype == np.uint16 and np.array_equal(got, img16)
    rgb = np.stack([scene.image] * 3, -1)
    Image.fromarray(rgb).save(tmp_path / "b.jpg", quality=95)
    grey = di.read_image(tmp_path / "b.jpg")
    assert grey.shape == scene.image.shape and grey.dtype == np.uint8
    assert np.mean(np.abs(grey.astype(float) - scene.image)) < 2.0


@needs_model
def test_learned_detector_on_16_bit_and_jpeg_finds_the_same_craters(tmp_path: Path, scene,
                                                                   monkeypatch, capsys) -> None:
    Image.fromarray(scene.image.astype(np.uint16) * 250 + 300).save(tmp_path / "a.tif")
    Image.fromarray(np.stack([scene.image] * 3, -1)).save(tmp_path / "b.jpg", quality=95)
    Image.fromarray(scene.image).save(tmp_path / "c.png")
    code, out, err = _run(monkeypatch, capsys, str(tmp_path / "a.tif"), str(tmp_path / "b.jpg"),
                          str(tmp_path / "c.png"), "--out", str(tmp_path / "o"))
    assert code == 0, err
    t = pl.read_parquet(tmp_path / "o" / "detections.parquet")
    assert t.columns == list(di.DETECTIONS_SCHEMA)
    counts = t.group_by("image").len().sort("image")["len"].to_list()
    big = np.sum(2 * scene.semi_major_px >= 10)
    assert min(counts) >= 0.6 * big and max(counts) - min(counts) <= 0.1 * max(counts) + 1
    assert "Sun azimuth" in out and "estimated" in out


def test_labels_print_recall_and_precision(tmp_path: Path, scene, monkeypatch, capsys) -> None:
    Image.fromarray(scene.image).save(tmp_path / "s.png")
    r = np.sqrt(scene.semi_major_px * scene.semi_minor_px)
    keep = 2 * r >= 10
    lines = [f"0 {u / 256:.6f} {v / 256:.6f} {2 * rr / 256:.6f} {2 * rr / 256:.6f}"
             for (u, v), rr in zip(scene.centre_px[keep], r[keep], strict=True)]
    (tmp_path / "s.txt").write_text("\n".join(lines) + "\n")
    sun = np.degrees(np.arctan2(scene.sun_dir_image[1], scene.sun_dir_image[0]))
    code, out, _ = _run(monkeypatch, capsys, str(tmp_path / "s.png"), "--out",
                        str(tmp_path / "o"), "--labels", str(tmp_path / "s.txt"), "--detector",
                        "classical", "--sun-azimuth-deg", f"{sun:.3f}")
    assert code == 0
    assert "(given)" in out and "recall" in out and "10-20 px" in out
    c, d, _ = di.read_labels(tmp_path / "s.txt", (256, 256))
    np.testing.assert_allclose(d, 2 * r[keep], rtol=1e-4)
    np.testing.assert_allclose(c, scene.centre_px[keep], atol=1e-3)


def test_unknown_detector_is_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    code, _, err = _run(monkeypatch, capsys, "x.png", "--out", str(tmp_path), "--detector",
                        "magic")
    assert code == 1 and err.count("\n") == 1 and "unknown detector 'magic'" in err


@needs_model
def test_wide_image_is_tiled(tmp_path: Path, monkeypatch, capsys) -> None:
    """10,000 px wide: three tiles across, every crater once."""
    rng = np.random.default_rng(5)
    strip = np.concatenate([render_scene(scene_rng(123, k), SceneOptions(size_px=256)).image
                            for k in range(40)], axis=1)[:, :10_000]
    strip = strip + rng.integers(0, 2, strip.shape).astype(np.uint8)
    Image.fromarray(strip).save(tmp_path / "wide.png")
    code, out, err = _run(monkeypatch, capsys, str(tmp_path / "wide.png"), "--out",
                          str(tmp_path / "o"))
    assert code == 0, err
    assert "10000 x 256 px" in out
    t = pl.read_parquet(tmp_path / "o" / "detections.parquet")
    c = t.select("centre_u_px", "centre_v_px").to_numpy()
    d = np.linalg.norm(c[:, None] - c[None], axis=-1) + np.eye(len(c)) * 1e9
    assert t.height > 100 and d.min() > 1.0  # no crater twice


@pytest.mark.slow
@needs_model
def test_ten_thousand_px_square_image(tmp_path: Path, monkeypatch, capsys) -> None:
    tile = render_scene(scene_rng(321, 0), SceneOptions(size_px=500)).image
    big = np.tile(tile, (20, 20))
    Image.fromarray(big).save(tmp_path / "big.png")
    code, out, err = _run(monkeypatch, capsys, str(tmp_path / "big.png"), "--out",
                          str(tmp_path / "o"))
    assert code == 0, err
    assert "10000 x 10000 px" in out
    with Image.open(tmp_path / "o" / "big_overlay.png") as im:
        assert max(im.size) == di.OVERLAY_MAX_PX


def test_a_few_labels_outside_the_image_are_left_out_and_counted(tmp_path: Path) -> None:
    """A label whose crater does not meet the image (one of the real sets has 4 such rows of
    1,277) cannot be found: it is left out of the score, and counted."""
    f = tmp_path / "l.csv"
    f.write_text("ID,X,Y,W,H,C_X,CY\n1,10,10,8,8,14,14\n2,50,50,12,12,56,56\n"
                 "3,60,962,12,12,66,968\n")
    lab = di.read_labels(f, (800, 800))
    assert lab.n_outside == 1
    np.testing.assert_allclose(lab.centre_px, [[14, 14], [56, 56]])
    np.testing.assert_allclose(lab.diam_px, [8, 12])
