"""Train pcdiff_jax: stage 1 (scene encoder) and stage 2 (latent diffusion).

  python -m experiments.train --stage encoder --config cpu --data 'data/synth/train-*' --workdir runs/cpu

Validation reads --val-data (default: the --data pattern with 'train' replaced
by 'val', when such files exist). Examples are cached under WORKDIR/cache.
Run the same command again after an interruption: it resumes from the last
checkpoint in WORKDIR/<stage>/checkpoints. Scalars: WORKDIR/<stage>/tb
(TensorBoard) and WORKDIR/<stage>/metrics.jsonl.

Every device is used: the global --batch-size is split over a `data` mesh axis
(a multiple of the device count; --devices N takes the first N). Several hosts:
run the same command on each with --coordinator HOST:PORT --num-processes N
--process-id I (or JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID;
--distributed lets JAX read them from SLURM / Open MPI / Cloud TPU); each host
reads every N-th --data file from its own index, WORKDIR must be shared, and a
run resumes on any device count.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

from experiments import _args
from pcdiff_jax import config as config_lib
from pcdiff_jax.data import womd

STAGES = ("encoder", "diffusion", "all")


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.train", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--stage", default="encoder", choices=STAGES)
  p.add_argument("--config", default="cpu", choices=sorted(config_lib.PRESETS))
  p.add_argument("--data", required=True, nargs="+", help="training TFRecord file(s) or glob(s)")
  p.add_argument("--val-data", nargs="+", default=None,
                 help="validation TFRecords (default: --data with 'train' -> 'val')")
  p.add_argument("--workdir", required=True, type=_args.output_dir)
  p.add_argument("--cache-dir", default=None, type=_args.output_dir,
                 help="where example caches are kept (default WORKDIR/cache); share it between runs")
  p.add_argument("--steps", type=int, default=None, help="override total optimizer steps")
  p.add_argument("--batch-size", type=int, default=None)
  p.add_argument("--max-minutes", type=float, default=None,
                 help="stop (and checkpoint) after this wall time")
  p.add_argument("--limit", type=int, default=None, help="use only the first N training scenes")
  p.add_argument("--no-prior", action="store_true",
                 help="stage 2: the context-only ablation (no proposal tokens, N(0, I) start)")
  p.add_argument("--bfloat16", action="store_true", help="stage 2: denoiser matmuls in bfloat16")
  p.add_argument("--no-progress", action="store_true")
  _args.add_device_flags(p)
  args = p.parse_args(argv)
  for name in ("steps", "batch_size", "limit"):
    v = getattr(args, name)
    if v is not None and v < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  _args.check_device_flags(p, args)
  return args


def _val_paths(args) -> list[str]:
  if args.val_data:
    return womd.expand_paths(args.val_data)
  guesses = [d.replace("train", "val") for d in args.data if "train" in d]
  try:
    return womd.expand_paths(guesses) if guesses else []
  except FileNotFoundError:
    return []


def resolve_config(args) -> config_lib.Config:
  cfg = config_lib.get_config(args.config)
  overrides = {}
  if args.steps is not None:
    overrides["total_steps"] = args.steps
  if args.batch_size is not None:
    overrides["batch_size"] = args.batch_size
  if overrides:
    cfg = dataclasses.replace(
        cfg, encoder_train=dataclasses.replace(cfg.encoder_train, **overrides),
        diffusion_train=dataclasses.replace(cfg.diffusion_train, **overrides))
  den = cfg.diffusion.denoiser
  if args.no_prior:
    den = dataclasses.replace(den, use_prior=False)
  if args.bfloat16:
    den = dataclasses.replace(den, compute_dtype="bfloat16")
  cfg = dataclasses.replace(cfg, diffusion=dataclasses.replace(cfg.diffusion, denoiser=den))
  return cfg


def _mesh(args, cfg: config_lib.Config):
  """The data mesh over --devices (None on a single device: the one-device
  step, unchanged); ValueError when a trained stage's batch does not split."""
  import jax

  from pcdiff_jax import distributed
  mesh = _args.device_mesh(args)
  if mesh is None:
    return None
  stages = {"encoder": ("encoder",), "diffusion": ("diffusion",), "all": ("encoder", "diffusion")}
  for stage in stages[args.stage]:
    size = getattr(cfg, f"{stage}_train").batch_size
    distributed.check_divisible(size, mesh, f"the {stage} batch size (--batch-size)")
  print(f"data-parallel over {mesh.devices.size} device(s) ({jax.devices()[0].platform}), "
        f"{jax.process_count()} process(es)")
  return mesh


def main(argv=None) -> int:
  args = parse_args(argv)
  _args.setup_logging()
  import jax

  from pcdiff_jax import distributed
  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import encoder_stage, trainer
  cfg = resolve_config(args)
  try:
    mesh = _mesh(args, cfg)
    train_files = womd.expand_paths(args.data)
    if jax.process_count() > 1:   # each host reads its own files
      train_files = distributed.host_shard(train_files)
    val_files = _val_paths(args)
    cache = args.cache_dir or os.path.join(args.workdir, "cache")
    spec = encoder_stage.cache_spec(cfg)
    train, info = data_lib.load_or_build(train_files, spec, cache, "train",
                                         progress=not args.no_progress, limit=args.limit)
    print(f"train: {data_lib.num_examples(train)} examples from {len(train_files)} file(s), "
          f"{info['skipped']} bad record(s) skipped")
    val = None
    if val_files:
      val, vinfo = data_lib.load_or_build(val_files, spec, cache, "val", progress=not args.no_progress)
      print(f"val: {data_lib.num_examples(val)} examples from {len(val_files)} file(s), "
            f"{vinfo['skipped']} bad record(s) skipped")
    else:
      print("val: none (no --val-data and no matching val files); validation is skipped")
    from pcdiff_jax.training import diffusion_stage
    results = {}
    if args.stage in ("encoder", "all"):
      state, metrics = encoder_stage.train(cfg, train, val, args.workdir, max_minutes=args.max_minutes,
                                           progress=not args.no_progress, mesh=mesh)
      results["encoder"] = {"step": int(state.step), "val": metrics}
    if args.stage in ("diffusion", "all"):
      state, metrics = diffusion_stage.train(cfg, train, val, args.workdir,
                                             max_minutes=args.max_minutes,
                                             progress=not args.no_progress, mesh=mesh)
      results["diffusion"] = {"step": int(state.step), "val": metrics}
  except (FileNotFoundError, ValueError, trainer.CheckpointMismatch) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    return 130
  out = {"stage": args.stage, "config": args.config, **results}
  if not distributed.is_primary():
    return 0
  with open(os.path.join(args.workdir, f"{args.stage}_summary.json"), "w") as f:
    json.dump(out, f, indent=2)
  print(json.dumps(out, indent=2))
  print(f"wrote {args.workdir}/{args.stage}_summary.json; checkpoints in the stage folders under {args.workdir}/")
  return 0


if __name__ == "__main__":
  sys.exit(main())
