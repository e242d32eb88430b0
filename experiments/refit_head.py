"""Refit the encoder's proposal head on real and synthetic logged scenes (trunk frozen).

  python -m experiments.refit_head --from checkpoints/pcdiff-cpu-v8 --data 'data/synth600/train-*' \\
      --real-data ../shared/data/womd_real/train.scenario.tfrecord --real-share 0.5 \\
      --val-data ../shared/data/womd_real/val.scenario.tfrecord --steps 10000 --workdir runs/head

Writes WORKDIR/encoder (--from's encoder with the refit head: `--method
simpl-ar --checkpoint WORKDIR` runs it), WORKDIR/diffusion (--from's denoiser
on the refit encoder, not re-trained: `--method pcdiff --checkpoint WORKDIR`)
and WORKDIR/refit_summary.json (the prediction metrics of every --val-data
file before and after, and the speed bias of the most likely proposal:
`pcdiff_jax.training.head_refit`). The denoiser reads the proposals too;
re-train it on the new ones:

  python -m experiments.finetune --from checkpoints/pcdiff-cpu-v8 --encoder-from runs/head \\
      --data 'data/synth600/train-*' --workdir runs/v10 --rounds 2 --scenes 150 --steps 800

Run the same command again after an interruption: the head resumes.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

from experiments import _args
from pcdiff_jax.data import womd


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.refit_head", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--from", dest="source", required=True, help="a model folder with encoder/")
  p.add_argument("--data", required=True, nargs="+", help="synthetic (or any) training TFRecord file(s) or glob(s)")
  p.add_argument("--real-data", nargs="+", default=None, metavar="FILE", help="real WOMD training scenes")
  p.add_argument("--real-share", type=float, default=0.5, help="share of each batch from --real-data")
  p.add_argument("--val-data", nargs="+", default=[], metavar="FILE",
                 help="scenes to report the prediction metrics on, each file on its own")
  p.add_argument("--workdir", required=True, type=_args.output_dir)
  p.add_argument("--cache-dir", default=None, type=_args.output_dir, help="logged-example cache (default WORKDIR/cache)")
  p.add_argument("--steps", type=int, default=10000)
  p.add_argument("--learning-rate", type=float, default=3e-4)
  p.add_argument("--batch-size", type=int, default=32)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--no-progress", action="store_true")
  args = p.parse_args(argv)
  if args.steps < 1 or args.batch_size < 2:
    p.error("--steps must be >= 1 and --batch-size >= 2")
  if not 0.0 < args.real_share < 1.0:
    p.error("--real-share must be in (0, 1)")
  if args.learning_rate <= 0:
    p.error("--learning-rate must be > 0")
  return args


def _write_denoiser(source: str, workdir: str, encoder_params) -> None:
  """WORKDIR/diffusion := SOURCE's stage-2 checkpoint with ENCODER_PARAMS as
  its frozen encoder (the one the diffusion policy reads), when SOURCE has one."""
  from pcdiff_jax.training import diffusion_stage, trainer
  stage = diffusion_stage.stage_dir(True)
  if not os.path.isdir(os.path.join(source, stage)):
    return
  src = trainer.Checkpointer(os.path.join(source, stage), read_only=True)
  try:
    step, config, raw = src.latest_step(), src.read_config(), src.restore_raw()
  finally:
    src.close()
  raw["extra"]["encoder"] = encoder_params
  dst = trainer.Checkpointer(os.path.join(workdir, stage), keep=1)
  try:
    dst.save_raw(step, raw, config)
  finally:
    dst.close()


def main(argv=None) -> int:
  args = parse_args(argv)
  _args.setup_logging()
  from pcdiff_jax import config as config_lib
  from pcdiff_jax.training import data as data_lib, encoder_stage, head_refit, trainer
  try:
    if os.path.abspath(args.workdir) == os.path.abspath(args.source):
      raise ValueError("--workdir must differ from --from (the model started from stays as it is)")
    if not os.path.isdir(os.path.join(args.source, encoder_stage.STAGE_DIR)):
      raise FileNotFoundError(f"--from {args.source}: no {encoder_stage.STAGE_DIR}/ model folder there")
    params, cfg = encoder_stage.load(args.source)
    tc = dataclasses.replace(cfg.encoder_train, total_steps=args.steps, learning_rate=args.learning_rate,
                             batch_size=args.batch_size, warmup_steps=min(100, args.steps // 10),
                             checkpoint_every=min(500, args.steps), eval_every=args.steps, seed=args.seed,
                             final_lr_fraction=0.05)
    cfg = dataclasses.replace(cfg, encoder_train=tc)
    spec = encoder_stage.cache_spec(cfg)
    cache = args.cache_dir or os.path.join(args.workdir, "cache")
    load = lambda paths, split: data_lib.load_or_build(womd.expand_paths(paths), spec, cache, split,
                                                        progress=not args.no_progress)[0]
    t0 = time.time()
    sources, shares = [head_refit.trunk_outputs(params, cfg, load(args.data, "train"))], [1.0]
    if args.real_data:
      sources.insert(0, head_refit.trunk_outputs(params, cfg, load(args.real_data, "real")))
      shares = [args.real_share, 1.0 - args.real_share]
    vals = {path: head_refit.trunk_outputs(params, cfg, load([path], f"val{i}"))
            for i, path in enumerate(args.val_data)}
    before = {path: head_refit.evaluate(head_refit.head_params(params), cfg, v) for path, v in vals.items()}
    refit = head_refit.refit(params, cfg, sources, shares, tc, os.path.join(args.workdir, "head"),
                             config_lib.to_dict(cfg), progress=not args.no_progress)
    after = {path: head_refit.evaluate(head_refit.head_params(refit), cfg, v) for path, v in vals.items()}
    src = trainer.Checkpointer(os.path.join(args.source, encoder_stage.STAGE_DIR), read_only=True)
    try:
      raw = src.restore_raw()
    finally:
      src.close()
    out = trainer.Checkpointer(os.path.join(args.workdir, encoder_stage.STAGE_DIR), keep=1)
    try:
      out.save_raw(args.steps, {"step": raw["step"], "params": refit, "rng": raw["rng"]}, config_lib.to_dict(cfg))
    finally:
      out.close()
    _write_denoiser(args.source, args.workdir, refit)
    summary = {"from": args.source, "args": vars(args), "minutes": (time.time() - t0) / 60,
               "val": {path: {"before": before[path], "after": after[path]} for path in vals}}
    with open(os.path.join(args.workdir, "refit_summary.json"), "w") as f:
      json.dump(summary, f, indent=2)
    for path in vals:
      for when, m in (("before", before[path]), ("after", after[path])):
        print(f"{path} {when}: minADE6 {m['min_ade']:.3f} minFDE6 {m['min_fde']:.3f} "
              f"brier-minFDE {m['brier_min_fde']:.3f} miss {m['miss_rate']:.3f} "
              f"speed bias 1 s {m['speed_bias_1s']:+.2f} 3 s {m['speed_bias_3s']:+.2f} m/s")
    print(f"wrote {args.workdir}/{encoder_stage.STAGE_DIR}, diffusion/ (where --from has one) and "
          f"{args.workdir}/refit_summary.json")
  except (FileNotFoundError, ValueError, trainer.CheckpointMismatch) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    return 130
  return 0


if __name__ == "__main__":
  sys.exit(main())
