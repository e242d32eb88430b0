"""Open-loop sampler quality of trained stage-2 models (the issue-5 table).

  python -m experiments.open_loop --workdir runs/cpu --data 'data/synth/val-*' \
      --ddim-steps 5 10 25 --samples 6 --out runs/cpu/open_loop

For each variant found in WORKDIR (diffusion = with the proposal prior,
started from the shifted Gaussian; diffusion_noprior = context only, started
from N(0, I)) and each DDIM step count: minADE / minFDE over N sampled joint
plans of the agents with a fully valid 8 s future at t = 10, the mean ADE of
a sample, and the fraction of sampled scenes where two agents' boxes overlap
at some step (the synthetic logs have none: `stats.json`). Writes
OUT/open_loop.json and OUT/open_loop.md.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys

from experiments import _args, _report
import time


def parse_args(argv=None):
  p = argparse.ArgumentParser(prog="python -m experiments.open_loop", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--workdir", required=True)
  p.add_argument("--data", required=True, nargs="+", help="validation TFRecords")
  p.add_argument("--ddim-steps", type=int, nargs="+", default=[5, 10, 25])
  p.add_argument("--samples", type=int, default=6)
  p.add_argument("--eta", type=float, default=0.0)
  p.add_argument("--batch-size", type=int, default=8)
  p.add_argument("--limit", type=int, default=None, help="first N scenes only")
  p.add_argument("--out", required=True, type=_args.output_dir)
  args = p.parse_args(argv)
  if min(args.ddim_steps) < 1 or args.samples < 1:
    p.error("--ddim-steps and --samples must be >= 1")
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  logging.basicConfig(level=logging.WARNING)
  import dataclasses

  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import diffusion_stage, encoder_stage
  rows = []
  try:
    variants = [(p, name) for p, name in ((True, "prior"), (False, "no prior"))
                if os.path.isdir(os.path.join(args.workdir, diffusion_stage.stage_dir(p)))]
    if not variants:
      raise FileNotFoundError(f"no stage-2 checkpoint in {args.workdir} (train --stage diffusion first)")
    for use_prior, name in variants:
      models, cfg = diffusion_stage.load(args.workdir, use_prior)
      cfg = dataclasses.replace(cfg, diffusion=dataclasses.replace(cfg.diffusion, eta=args.eta))
      spec = dataclasses.replace(encoder_stage.cache_spec(cfg), current_steps=(10,))
      ex, info = data_lib.load_or_build(args.data, spec, os.path.join(args.workdir, "cache"), "val",
                                        limit=args.limit)
      ex = diffusion_stage.full_future_examples(ex)
      extra = {"encoder": models.encoder, "stats": models.stats}
      for steps in args.ddim_steps:
        ev = diffusion_stage.make_evaluate(cfg, ex, args.batch_size, args.samples, steps,
                                           prior_init=use_prior)
        t0 = time.time()
        m = ev(models.denoiser, extra)
        m.update(variant=name, ddim_steps=steps, samples=args.samples, scenes=data_lib.num_examples(ex),
                 seconds=time.time() - t0, skipped=info["skipped"])
        rows.append(m)
        print(f"{name:9s} {steps:3d} steps: minADE {m['min_ade']:.3f} minFDE {m['min_fde']:.3f} "
              f"overlap {m['overlap_rate']:.3f} ({m['seconds']:.0f} s)", flush=True)
  except (FileNotFoundError, ValueError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  lines = [f"| variant | DDIM steps | minADE{args.samples} (m) | minFDE{args.samples} (m) | "
           "mean ADE (m) | scenes with overlap |", "|---|---|---|---|---|---|"]
  for r in rows:
    lines.append(f"| {r['variant']} | {r['ddim_steps']} | {r['min_ade']:.3f} | {r['min_fde']:.3f} | "
                 f"{r['mean_ade']:.3f} | {r['overlap_rate']:.3f} |")
  table = "\n".join(lines) + "\n"
  _report.write(args.out, "open_loop", rows, table)
  return 0


if __name__ == "__main__":
  sys.exit(main())
