"""Training the learned crater detector on the CPU, reproducibly from a seed, and its export to
ONNX with a JSON of how it was trained.

Two phases (fixed step counts, so the same seed gives the same weights on the same machine):
1. synthetic: crops of rendered scenes (`pipeline.core.sensors.scenes`, domain-randomised, with
   degraded craters), `steps_synthetic` steps;
2. mixed: half the batch crops of the real labelled images (all but the left-out ones), half
   rendered, `steps_real` steps, from phase 1's weights (shared by the leave-one-out folds).
Loss (CenterNet, Zhou et al. 2019): the penalty-reduced focal loss on the heatmap (alpha 2, beta
4; Lin et al. 2017, "Focal loss for dense object detection") normalised by the positives, plus L1
on log radius and on the centre offset over each crater's regression area, weighted by its
heatmap (`data.targets`). AdamW (Loshchilov & Hutter 2019), one-cycle learning rate (Smith &
Topin 2019).

Batch normalisation's statistics are frozen for the last `bn_frozen_share` of each phase (the
layers normalise with their running averages, as at inference, while the weights keep learning),
so the network is trained in the form it is used in.

Speed: on a CPU with bfloat16 instructions (AVX512-BF16 or AMX; `bf16_supported`), the forward
pass runs under bfloat16 autocast with channels-last tensors (weights, optimiser and loss in
float32): 3.5x faster per step on the 2-core AMD EPYC this was written on (0.35 -> 0.10 s for a
batch of 16 crops of 256 px). Elsewhere float32. The mode is recorded in the model's JSON; the
same seed gives the same weights on the same kind of CPU.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from pipeline.core.sensors.scenes import SceneOptions
from pipeline.ops.detectors import MODEL_FORMAT
from pipeline.train import data
from pipeline.train.model import BLOCKS, CHANNELS, HEAD_CHANNELS, OUTPUTS, STRIDE, CraterNet


@dataclass(frozen=True)
class TrainOptions:
    """What a training run does; every number of it is recorded in the model's JSON."""

    seed: int = 20261207
    scenes: int = 3000
    crop_px: int = 256
    batch: int = 16
    steps_synthetic: int = 3000
    steps_real: int = 3000
    lr: float = 3e-3
    weight_decay: float = 1e-4
    real_scale: tuple[float, float] = (1.0, 1.0)  # shrink factor of the real crops (<= 1)
    photometric_share: float = 0.5
    bn_frozen_share: float = 0.2
    bf16: bool | None = None  # None: where the CPU has bfloat16 instructions
    threads: int = 2  # scene rendering processes, and the network's threads (a second process
    # draws the batches ahead)
    scene: SceneOptions = field(default_factory=SceneOptions)


def focal_loss(logit: torch.Tensor, heat: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss summed over cells, per positive."""
    p = torch.sigmoid(logit).clamp(1e-4, 1 - 1e-4)
    pos = heat >= 1.0
    pos_loss = -(torch.log(p) * (1 - p) ** 2)[pos].sum()
    neg_loss = -(torch.log(1 - p) * p ** 2 * (1 - heat) ** 4 * weight)[~pos].sum()
    return (pos_loss + neg_loss) / pos.sum().clamp(min=1)


def loss_fn(out: torch.Tensor, tg: tuple[torch.Tensor, ...]) -> tuple[torch.Tensor, dict]:
    heat, weight, reg, log_r, off = tg
    lf = focal_loss(out[:, 0], heat, weight)
    n = reg.sum().clamp(min=1e-3)
    lr = (torch.abs(out[:, 1] - log_r) * reg).sum() / n
    lo = (torch.abs(out[:, 2:4] - off) * reg[:, None]).sum() / n
    return lf + lr + lo, {"focal": lf.item(), "log_r": lr.item(), "offset": lo.item()}


def bf16_supported() -> bool:
    """Whether this CPU runs bfloat16 natively (AVX512-BF16 or AMX), as PyTorch reports it."""
    try:
        return bool(torch.backends.mkldnn.is_available()
                    and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):
        return False


def _use_bf16(opts: TrainOptions) -> bool:
    return bf16_supported() if opts.bf16 is None else opts.bf16


Draw = Callable[[int], tuple[np.ndarray, ...]]


def _producer(draw: Draw, steps: int, queue: mp.Queue) -> None:
    for step in range(steps):
        queue.put(draw(step))


def prefetched(draw: Draw, steps: int) -> Iterator[tuple[np.ndarray, ...]]:
    """draw(0), ..., draw(steps - 1), drawn in order by one forked process ahead of the
    consumer (the same batches as drawing them here)."""
    ctx = mp.get_context("fork")
    queue = ctx.Queue(maxsize=8)
    proc = ctx.Process(target=_producer, args=(draw, steps, queue), daemon=True)
    proc.start()
    try:
        for _ in range(steps):
            yield queue.get()
    finally:
        proc.join(timeout=5)
        if proc.is_alive():
            proc.terminate()


def _steps(model: CraterNet, steps: int, draw: Draw, opts: TrainOptions, log: list[dict],
           phase: str) -> None:
    """`steps` optimiser steps on batches from draw(step) -> numpy batch."""
    torch.set_num_threads(opts.threads)
    bf16 = _use_bf16(opts)
    model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    optim = torch.optim.AdamW(model.parameters(), lr=opts.lr, weight_decay=opts.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(optim, max_lr=opts.lr, total_steps=steps,
                                                pct_start=0.1)
    model.train()
    freeze_at = round((1.0 - opts.bn_frozen_share) * steps)
    t0 = time.perf_counter()
    acc: dict[str, float] = {}
    for step, arrays in enumerate(prefetched(draw, steps)):
        if step == freeze_at:
            for layer in model.modules():
                if isinstance(layer, torch.nn.BatchNorm2d):
                    layer.eval()
        x, *tg = (torch.from_numpy(a) for a in arrays)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = model(x.contiguous(memory_format=torch.channels_last))
        loss, parts = loss_fn(out.float(), tuple(tg))
        optim.zero_grad()
        loss.backward()
        optim.step()
        sched.step()
        for k, v in parts.items():
            acc[k] = acc.get(k, 0.0) + v
        if (step + 1) % 100 == 0 or step + 1 == steps:
            n = (step % 100) + 1
            log.append({"phase": phase, "step": step + 1, "s": time.perf_counter() - t0,
                        **{k: v / n for k, v in acc.items()}})
            print(f"  {phase} {step + 1}/{steps} ({time.perf_counter() - t0:.0f} s) "
                  + " ".join(f"{k} {v / n:.3f}" for k, v in acc.items()), flush=True)
            acc = {}


def pretrain(opts: TrainOptions, log: list[dict]) -> tuple[CraterNet, list[data.Labelled]]:
    """Phase 1: the network trained on rendered scenes alone; returns it and the scenes."""
    torch.manual_seed(opts.seed)
    t0 = time.perf_counter()
    scenes = data.rendered_set(opts.seed, opts.scenes, opts.scene, workers=opts.threads)
    log.append({"phase": "render", "scenes": len(scenes), "s": time.perf_counter() - t0})
    print(f"  rendered {len(scenes)} scenes in {time.perf_counter() - t0:.0f} s", flush=True)
    model = CraterNet()
    rng = np.random.default_rng([opts.seed, 1])

    def draw(step: int) -> tuple[np.ndarray, ...]:
        pick = rng.integers(0, len(scenes), opts.batch)
        return data.batch([scenes[k] for k in pick], opts.crop_px, rng, (1.0, 1.0),
                          opts.photometric_share)

    _steps(model, opts.steps_synthetic, draw, opts, log, "synthetic")
    return model, scenes


def finetune(model: CraterNet, scenes: list[data.Labelled], real: list[data.Labelled],
             opts: TrainOptions, log: list[dict], tag: int = 0) -> CraterNet:
    """Phase 2 on a copy of `model`: half real crops, half rendered (rendered only without real
    images); `tag` separates the random streams of several fine-tunings."""
    tuned = CraterNet()
    tuned.load_state_dict(model.state_dict())
    torch.manual_seed(opts.seed + 7919 * (tag + 1))
    rng = np.random.default_rng([opts.seed, 2, tag])
    half = opts.batch // 2 if real else 0

    def draw(step: int) -> tuple[np.ndarray, ...]:
        r = [real[k] for k in rng.integers(0, len(real), half)] if half else []
        s = [scenes[k] for k in rng.integers(0, len(scenes), opts.batch - half)]
        br = data.batch(r, opts.crop_px, rng, opts.real_scale, opts.photometric_share) \
            if r else None
        bs = data.batch(s, opts.crop_px, rng, (1.0, 1.0), opts.photometric_share)
        return bs if br is None else tuple(np.concatenate(p) for p in zip(br, bs, strict=True))

    _steps(tuned, opts.steps_real, draw, opts, log, "mixed")
    return tuned


def export(model: CraterNet, path: Path, facts: dict) -> None:
    """The model as ONNX (input `image` (1, 1, H, W), output `maps` (1, 4, H/4, W/4), dynamic
    sides) at `path`, and the facts as JSON beside it (same stem)."""
    model.eval()
    model.to(memory_format=torch.contiguous_format)  # type: ignore[call-overload]
    path.parent.mkdir(parents=True, exist_ok=True)
    x = torch.zeros(1, 1, 256, 256)
    tmp = path.with_suffix(".tmp.onnx")
    torch.onnx.export(model, (x,), str(tmp), input_names=["image"], output_names=["maps"],
                      dynamic_axes={"image": {2: "height", 3: "width"},
                                    "maps": {2: "height4", 3: "width4"}},
                      opset_version=17, dynamo=False)
    tmp.replace(path)
    sha256 = hashlib.sha256(path.read_bytes()).hexdigest()  # checked where it is loaded
    path.with_suffix(".json").write_text(json.dumps({**facts, "sha256": sha256}, indent=2)
                                         + "\n")


def git_commit() -> str:
    """The checkout's commit (with '+dirty' when the tree has changes), or 'unknown'."""
    try:
        rev = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return rev + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def facts_of(opts: TrainOptions, real: list[data.Labelled], left_out: list[str], log: list[dict],
             seconds: float) -> dict:
    """The JSON written beside a model: how it was trained and its output layout."""
    return {"format": MODEL_FORMAT, "stride": STRIDE, "outputs": list(OUTPUTS),
            "input": "normalised image turned to the canonical Sun (+u)",
            "channels": list(CHANNELS), "blocks": list(BLOCKS), "head_channels": HEAD_CHANNELS,
            "options": asdict(opts), "bf16": _use_bf16(opts),
            "real_images": [r.name for r in real], "left_out": left_out,
            "commit": git_commit(), "torch": torch.__version__, "train_s": round(seconds, 1),
            "log": log}


def train_loss_on(model: CraterNet, samples: list[data.Labelled], opts: TrainOptions) -> float:
    """Mean loss over one deterministic batch of crops of `samples` (a smoke check)."""
    rng = np.random.default_rng(0)
    x, *tg = (torch.from_numpy(a) for a in data.batch(samples[:opts.batch], opts.crop_px, rng,
                                                       (1.0, 1.0), 0.0))
    model.eval()
    with torch.no_grad():
        return float(loss_fn(model(x), tuple(tg))[0])

