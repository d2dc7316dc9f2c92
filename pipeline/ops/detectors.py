"""Detectors by name, ready to run: the classical one, and the learned one with its network in
ONNX Runtime (the inference runtime lives here, outside the pure core).

`make_detector("classical" | "learned", ...)` returns an object with the `Detector` interface
(`pipeline.core.vision.detectors.base`). The learned detector's weights are
`pipeline/models/crater_detector.onnx` (trained by `just train-detector`, the JSON beside it says
how) unless a model path is given.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline.core.vision.detectors import DETECTOR_NAMES, ClassicalDetector, Detector
from pipeline.core.vision.detectors.classical import DetectOptions
from pipeline.core.vision.detectors.learned import LearnedDetector, LearnedOptions

MODELS = Path(__file__).resolve().parents[1] / "models"
DEFAULT_MODEL = MODELS / "crater_detector.onnx"
# the trained models key the stages that detect with them (`pipeline.engine.fingerprint`): a
# retrained or replaced model reruns them
KEYED_DATA = ("../models",)
MODEL_FORMAT = "crater-nav learned detector 2"  # the training's record (`pipeline.train.fit`)


@dataclass(frozen=True)
class OnnxNetwork:
    """A model file run by ONNX Runtime on the CPU with `threads` intra-op threads: called on an
    array (1, 1, H, W) float32, returns its first output."""

    path: Path
    threads: int = 2
    _session: object = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_session", _session(str(self.path), self.threads))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        sess = self._session
        name = sess.get_inputs()[0].name  # type: ignore[attr-defined]
        return sess.run(None, {name: np.ascontiguousarray(x, np.float32)})[0]  # type: ignore[attr-defined]


@functools.lru_cache(maxsize=4)
def _session(path: str, threads: int) -> object:
    """An ONNX Runtime session (cached per file and thread count)."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"no detector model at {path} (train one: just train-detector)")
    facts = model_facts(Path(path))
    if facts.get("format") not in (None, MODEL_FORMAT):
        raise ValueError(f"{path}: a model of another format ({facts.get('format')!r}, this "
                         f"detector runs {MODEL_FORMAT!r}: its input convention differs); "
                         "retrain it (just train-detector)")
    recorded = facts.get("sha256")
    if recorded is not None and hashlib.sha256(Path(path).read_bytes()).hexdigest() != recorded:
        raise ValueError(f"{path}: not the model its training recorded (sha256 differs from "
                         f"{Path(path).with_suffix('.json').name}); retrain or restore it")
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    try:
        return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime's own classes (InvalidProtobuf, Fail, ...)
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{path}: not a usable ONNX model ({first[:200]})") from None


def model_facts(path: Path = DEFAULT_MODEL) -> dict:
    """The training record beside a model (its .json: the training's facts and the model's
    sha256), {} when absent or unreadable."""
    meta = Path(path).with_suffix(".json")
    try:
        facts = json.loads(meta.read_text()) if meta.is_file() else {}
    except (OSError, ValueError):
        return {}
    return facts if isinstance(facts, dict) else {}


def make_detector(name: str, *, min_diameter_px: float = 10.0, blur_sigma_px: float = 0.0,
                  model: Path | None = None, threads: int = 2,
                  classical: DetectOptions | None = None, learned: LearnedOptions | None = None
                  ) -> Detector:
    """The detector called `name` (`DETECTOR_NAMES`) with the smallest diameter kept (px) and
    the camera's blur (px); options classes override the defaults; `model` the ONNX file of the
    learned one; `threads` the network's and the rim fits' (the same answer on any number)."""
    if name == ClassicalDetector.name:
        opts = classical or DetectOptions()
        return ClassicalDetector(replace(opts, min_diameter_px=min_diameter_px,
                                         psf_sigma_px=blur_sigma_px, threads=threads))
    if name == LearnedDetector.name:
        lo = learned or LearnedOptions()
        return LearnedDetector(OnnxNetwork(Path(model or DEFAULT_MODEL), threads),
                               replace(lo, min_diameter_px=min_diameter_px,
                                       psf_sigma_px=blur_sigma_px, threads=threads))
    raise ValueError(f"unknown detector {name!r}: one of {', '.join(DETECTOR_NAMES)}")
