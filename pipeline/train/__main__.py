"""`python -m pipeline.train` (`just train-detector`): train the learned crater detector.

Default: phase 1 on rendered scenes, phase 2 with every real labelled image of
`../shared/data/lro_nac_craters` (when present), written to `pipeline/models/crater_detector.onnx`
(+ .json); plus the fold that leaves out the first real image (`crater_detector_loo_<name>.onnx`,
for the left-out-image test), fine-tuned from the same phase 1. `--loo DIR`: every
leave-one-image-out fold into DIR (for the benchmark; one phase 1, a fine-tuning per image).
`--tiny`: a few steps on a few small scenes (CI's smoke run) into `--out`.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

try:  # the optional `train` extra: one line without it, not a traceback
    import torch  # noqa: F401
except ModuleNotFoundError:
    sys.exit('error: training needs PyTorch (the `train` extra): pip install -e ".[train]"')

from pipeline.core.sensors.scenes import SceneOptions
from pipeline.train import data
from pipeline.train.fit import TrainOptions, export, facts_of, finetune, pretrain
from pipeline.workspace import workspace

MODELS = Path(__file__).resolve().parents[1] / "models"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="just train-detector", description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=MODELS / "crater_detector.onnx")
    ap.add_argument("--seed", type=int, default=TrainOptions.seed)
    ap.add_argument("--real", type=Path, default=None,
                    help="folder of labelled real images (default ../shared/data/lro_nac_craters)")
    ap.add_argument("--no-real", action="store_true", help="rendered scenes only")
    ap.add_argument("--loo", type=Path, default=None, metavar="DIR",
                    help="write every leave-one-image-out fold into DIR instead")
    ap.add_argument("--groups", type=int, default=None,
                    help="with --loo: leave out groups of images (N folds of consecutive "
                         "images in name order) instead of one image at a time")
    ap.add_argument("--tiny", action="store_true", help="a smoke run of a few seconds")
    args = ap.parse_args(argv)
    opts = TrainOptions(seed=args.seed)
    if args.tiny:
        opts = replace(opts, scenes=6, steps_synthetic=6, steps_real=4, batch=4, crop_px=128,
                       threads=1, scene=SceneOptions(size_px=128))
    folder = args.real or workspace().root.parent / "shared" / "data" / "lro_nac_craters"
    real = [] if args.no_real or not folder.is_dir() else data.real_images(folder)
    if args.tiny:
        real = [data.canonical_crop(r, 256, np.random.default_rng(0)) for r in real[:2]]
    if not real and not args.no_real:
        print(f"no labelled real images in {folder}: training on rendered scenes only")
    t0 = time.perf_counter()
    log: list[dict] = []
    model, scenes = pretrain(opts, log)
    t_pre = time.perf_counter() - t0
    if args.loo is not None:
        n = len(real) if args.groups is None else max(1, min(args.groups, len(real)))
        folds = [list(part) for part in np.array_split(np.arange(len(real)), n)]
        for k, fold in enumerate(folds):
            t1 = time.perf_counter()
            left = [real[i].name for i in fold]
            rest = [r for r in real if r.name not in left]
            fold_log = list(log)
            tuned = finetune(model, scenes, rest, opts, fold_log, tag=k + 1)
            facts = facts_of(opts, rest, left, fold_log, t_pre + time.perf_counter() - t1)
            for name in left:  # one file per image it never saw (the same network)
                out = args.loo / f"crater_detector_loo_{name}.onnx"
                export(tuned, out, facts)
                print(f"wrote {out}")
        return 0
    tuned = finetune(model, scenes, real, opts, log, tag=0)
    export(tuned, args.out, facts_of(opts, real, [], log, time.perf_counter() - t0))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB) in "
          f"{time.perf_counter() - t0:.0f} s")
    if real and not args.tiny:
        t1 = time.perf_counter()
        first, others = real[0], real[1:]
        fold_log = list(log)
        tuned = finetune(model, scenes, others, opts, fold_log, tag=1)
        out = args.out.with_name(f"crater_detector_loo_{first.name}.onnx")
        export(tuned, out, facts_of(opts, others, [first.name], fold_log,
                                    t_pre + time.perf_counter() - t1))
        print(f"wrote {out} (leaves out {first.name})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
