"""Closed-loop rollout and metrics over WOMD-format TFRecords.

  python -m experiments.rollout --scenarios '../shared/data/womd/*.tfrecord' --method cv --out runs/cv
  python -m experiments.rollout --scenarios 'data/synth/val-*' --method pcdiff --checkpoint runs/cpu \
      --ddim-steps 5 --num-rollouts 4 --seeds 3 --policy select_samples=4 --out runs/eval/pcdiff
  python -m experiments.rollout ... --method pcdiff --guidance adversarial --w-pursue 30 --eta 0.07

Writes OUT/metrics.json, OUT/metrics.md, OUT/scenarios.jsonl and OUT/gifs/.
Every device is used: each call's --batch-size x --num-rollouts rollouts are
split over them (a multiple of the device count; --devices N takes the first N),
with the one-device results.
"""
from __future__ import annotations

import argparse
import sys

from experiments import _args
from pcdiff_jax import evaluation
from pcdiff_jax.config import MetricsConfig
from pcdiff_jax.model.guidance import MODES as GUIDANCE_MODES
from pcdiff_jax.model.guidance import GuidanceConfig


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.rollout", description=__doc__, epilog=_args.policy_fields_epilog(),
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", required=True, nargs="+",
                 help="TFRecord file(s) or glob(s) of WOMD motion tf.Examples or Scenario protos")
  p.add_argument("--method", default="cv", choices=sorted(evaluation.METHODS) + list(evaluation.LEARNED))
  p.add_argument("--checkpoint", default=None,
                 help="training workdir or model folder of the learned methods (pcdiff, pcdiff-noprior, "
                      "simpl-ar; simpl-ar reads its own encoder, simpl_ar/, where the folder has one)")
  p.add_argument("--ego", default="log", choices=evaluation.EGOS,
                 help="the SDC's fixed policy: log replay (default) or IDM")
  _args.add_policy_flags(p)
  _args.add_map_flags(p)
  _args.add_start_flags(p)
  p.add_argument("--simpl-ar-sample", action="store_true",
                 help="simpl-ar: draw each agent's mode by its probability (default: the top mode)")
  p.add_argument("--num-rollouts", type=int, default=1,
                 help="stochastic rollouts per scenario (minADE takes the best)")
  p.add_argument("--seeds", type=int, default=1, help="repeat everything with this many seeds (mean, std)")
  p.add_argument("--out", required=True, type=_args.output_dir, help="output folder")
  p.add_argument("--max-scenarios", type=int, default=None, help="only the first N scenarios")
  p.add_argument("--num-steps", type=int, default=80)
  p.add_argument("--max-agents", type=int, default=64, help="reactive agents nearest the SDC")
  p.add_argument("--batch-size", type=int, default=1, help="scenarios per jitted call")
  p.add_argument("--gifs", type=int, default=1, help="how many scenarios to render as GIF")
  p.add_argument("--seed", type=int, default=0)
  g = p.add_argument_group("guidance (pcdiff, pcdiff-noprior)")
  g.add_argument("--guidance", default="none", choices=GUIDANCE_MODES)
  g.add_argument("--w-map", type=float, default=None,
                 help="weight of J_map (default: 100 for objective guidance, 1 for adversarial)")
  g.add_argument("--w-coll", type=float, default=None,
                 help="weight of J_coll (default: 10 for objective guidance, 1 for adversarial)")
  g.add_argument("--w-pursue", type=float, default=GuidanceConfig.w_pursue)
  g.add_argument("--eta", type=float, default=GuidanceConfig.eta, help="latent step size")
  g.add_argument("--guided-steps", type=int, default=GuidanceConfig.guided_steps,
                 help="the last K DDIM steps are guided")
  g.add_argument("--inner-steps", type=int, default=GuidanceConfig.inner_steps,
                 help="gradient steps per guided DDIM step")
  g.add_argument("--ibr-rounds", type=int, default=GuidanceConfig.ibr_rounds)
  g.add_argument("--adversary", type=int, default=-1,
                 help="object slot of the pursuer (default: the most threatening vehicle)")
  g.add_argument("--max-step", type=float, default=GuidanceConfig.max_step,
                 help="trust region: latent step per agent and inner step")
  g.add_argument("--field-size", type=int, default=GuidanceConfig.field_size,
                 help="cells per side of the road field J_map reads (2 m each, centred on the SDC); "
                      "agents beyond it get no map gradient")
  g.add_argument("--score-adversary", action="store_true",
                 help="score the ego against the most threatening agent in non-adversarial runs too")
  p.add_argument("--no-progress", action="store_true", help="no progress bar")
  _args.add_device_flags(p, hosts=False)
  args = p.parse_args(argv)
  _args.check_device_flags(p, args)
  if args.method in evaluation.LEARNED and not args.checkpoint:
    p.error(f"--method {args.method} needs --checkpoint WORKDIR")
  for name in ("num_steps", "max_agents", "batch_size", "num_rollouts", "seeds"):
    if getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  for name in ("ddim_steps", "replan_every"):
    if getattr(args, name) is not None and getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if args.max_scenarios is not None and args.max_scenarios < 1:
    p.error("--max-scenarios must be >= 1")
  if args.num_steps > 80:
    p.error("--num-steps must be <= 80 (WOMD has 80 future steps)")
  if args.gifs < 0:
    p.error("--gifs must be >= 0")
  if args.guidance != "none" and args.method not in ("pcdiff", "pcdiff-noprior"):
    p.error(f"--guidance {args.guidance} needs --method pcdiff or pcdiff-noprior")
  for name in ("guided_steps", "inner_steps", "ibr_rounds", "field_size"):
    if getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if args.eta < 0:
    p.error("--eta must be >= 0")
  if args.max_step <= 0:
    p.error("--max-step must be > 0")
  args.policy_config = _args.policy_config(p, args)
  args.map_crop = _args.map_crop(p, args)
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  _args.setup_logging()
  cfg = evaluation.EvalConfig(method=args.method, checkpoint=args.checkpoint, ego=args.ego,
                              policy=args.policy_config, num_rollouts=args.num_rollouts,
                              seeds=args.seeds, num_steps=args.num_steps, batch_size=args.batch_size,
                              gifs=args.gifs, seed=args.seed, score_adversary=args.score_adversary,
                              max_scenarios=args.max_scenarios, simpl_ar_sample=args.simpl_ar_sample, **args.map_crop,
                              **_args.start_options(args),
                              metrics=MetricsConfig(max_reactive_agents=args.max_agents),
                              guidance=GuidanceConfig(
                                  mode=args.guidance, w_map=args.w_map, w_coll=args.w_coll,
                                  w_pursue=args.w_pursue, eta=args.eta, max_step=args.max_step,
                                  guided_steps=args.guided_steps, inner_steps=args.inner_steps,
                                  ibr_rounds=args.ibr_rounds, adversary=args.adversary,
                                  field_size=args.field_size))
  try:
    mesh = _args.device_mesh(args)
    summary = evaluation.evaluate(args.scenarios, args.out, cfg, progress=not args.no_progress, mesh=mesh)
  except (FileNotFoundError, ValueError, RuntimeError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  with open(f"{args.out}/metrics.md") as f:
    print(f.read())
  if summary["lost_agents"]:
    print(f"warning: {summary['lost_agents']} controlled agent(s) vanished mid-rollout "
          f"(of {summary['controlled_agents']}); see {args.out}/scenarios.jsonl", file=sys.stderr)
  print(f"wrote {args.out}/metrics.json, metrics.md, scenarios.jsonl, gifs/")
  return 0


if __name__ == "__main__":
  sys.exit(main())
