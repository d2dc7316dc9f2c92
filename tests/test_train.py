"""Training the learned detector on a tiny budget (CI's smoke run): it runs, writes an ONNX model
that ONNX Runtime loads with the promised outputs, and the same seed gives the same model."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from pipeline.ops.detectors import MODEL_FORMAT, make_detector  # noqa: E402
from pipeline.train.__main__ import main  # noqa: E402


def _outputs(path: Path, x: np.ndarray) -> np.ndarray:
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return sess.run(None, {"image": x})[0]


@pytest.mark.slow
def test_tiny_training_is_reproducible(tmp_path: Path) -> None:
    a, b, c = tmp_path / "a.onnx", tmp_path / "b.onnx", tmp_path / "c.onnx"
    assert main(["--tiny", "--no-real", "--out", str(a)]) == 0
    assert main(["--tiny", "--no-real", "--out", str(b)]) == 0
    assert main(["--tiny", "--no-real", "--seed", "5", "--out", str(c)]) == 0
    x = np.random.default_rng(0).standard_normal((1, 1, 96, 160)).astype(np.float32)
    ya, yb, yc = _outputs(a, x), _outputs(b, x), _outputs(c, x)
    assert ya.shape == (1, 4, 24, 40)
    np.testing.assert_array_equal(ya, yb)
    assert not np.allclose(ya, yc)
    facts = json.loads(a.with_suffix(".json").read_text())
    assert facts["format"] == MODEL_FORMAT and isinstance(facts["bf16"], bool)
    assert facts["options"]["seed"] != 5 and facts["outputs"][0] == "heat_logit"
    assert facts["stride"] == 4 and facts["train_s"] > 0 and facts["commit"]
    assert [e["phase"] for e in facts["log"]][:1] == ["render"]
    # the detector runs it (the sha256 its training recorded checked on loading)
    img = np.random.default_rng(1).integers(0, 255, (64, 96)).astype(np.uint8)
    det = make_detector("learned", model=a, threads=1).detect(img, np.array([0.0, 1.0]))
    assert det.centre_px.shape[1] == 2
