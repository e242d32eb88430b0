"""Closed-loop rollout and metrics over WOMD-format TFRecords.

  python -m experiments.rollout --scenarios '../shared/data/womd/*.tfrecord' --method cv --out runs/cv
  python -m experiments.rollout --scenarios 'data/synth/val-*' --method pcdiff --checkpoint runs/cpu \
      --ddim-steps 5 --num-rollouts 4 --seeds 3 --out runs/eval/pcdiff

Writes OUT/metrics.json, OUT/metrics.md, OUT/scenarios.jsonl and OUT/gifs/.
"""
from __future__ import annotations

import argparse
import logging
import sys

from pcdiff_jax import evaluation
from pcdiff_jax.config import MetricsConfig


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.rollout", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", required=True, nargs="+",
                 help="TFRecord file(s) or glob(s) in the WOMD motion tf.Example schema")
  p.add_argument("--method", default="cv", choices=sorted(evaluation.METHODS) + list(evaluation.LEARNED))
  p.add_argument("--checkpoint", default=None,
                 help="training workdir of the learned methods (pcdiff, pcdiff-noprior, simpl-ar)")
  p.add_argument("--ego", default="log", choices=evaluation.EGOS,
                 help="the SDC's fixed policy: log replay (default) or IDM")
  p.add_argument("--ddim-steps", type=int, default=5)
  p.add_argument("--replan-every", type=int, default=1, help="steps between plans (1 = 10 Hz)")
  p.add_argument("--num-rollouts", type=int, default=1,
                 help="stochastic rollouts per scenario (minADE takes the best)")
  p.add_argument("--seeds", type=int, default=1, help="repeat everything with this many seeds (mean, std)")
  p.add_argument("--out", required=True, help="output folder")
  p.add_argument("--num-steps", type=int, default=80)
  p.add_argument("--max-agents", type=int, default=64, help="reactive agents nearest the SDC")
  p.add_argument("--batch-size", type=int, default=1, help="scenarios per jitted call")
  p.add_argument("--gifs", type=int, default=1, help="how many scenarios to render as GIF")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--no-progress", action="store_true", help="no progress bar")
  args = p.parse_args(argv)
  if args.method in evaluation.LEARNED and not args.checkpoint:
    p.error(f"--method {args.method} needs --checkpoint WORKDIR")
  for name in ("num_steps", "max_agents", "batch_size", "ddim_steps", "replan_every", "num_rollouts",
               "seeds"):
    if getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if args.num_steps > 80:
    p.error("--num-steps must be <= 80 (WOMD has 80 future steps)")
  if args.gifs < 0:
    p.error("--gifs must be >= 0")
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
  cfg = evaluation.EvalConfig(method=args.method, checkpoint=args.checkpoint, ego=args.ego,
                              ddim_steps=args.ddim_steps,
                              replan_every=args.replan_every, num_rollouts=args.num_rollouts,
                              seeds=args.seeds,
                              num_steps=args.num_steps, batch_size=args.batch_size,
                              gifs=args.gifs, seed=args.seed,
                              metrics=MetricsConfig(max_reactive_agents=args.max_agents))
  try:
    evaluation.evaluate(args.scenarios, args.out, cfg, progress=not args.no_progress)
  except (FileNotFoundError, ValueError, RuntimeError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  with open(f"{args.out}/metrics.md") as f:
    print(f.read())
  print(f"wrote {args.out}/metrics.json, metrics.md, scenarios.jsonl, gifs/")
  return 0


if __name__ == "__main__":
  sys.exit(main())
