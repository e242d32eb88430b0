"""Closed-loop rollout and metrics over WOMD-format TFRecords.

  python -m experiments.rollout --scenarios '../shared/data/womd/*.tfrecord' --method cv --out runs/cv
  python -m experiments.rollout --scenarios 'data/synth/val-*' --method pcdiff --checkpoint runs/cpu \
      --ddim-steps 5 --num-rollouts 4 --seeds 3 --out runs/eval/pcdiff
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
from pcdiff_jax.policy import PolicyConfig, with_overrides
from pcdiff_jax.config import MetricsConfig
from pcdiff_jax.model.guidance import MODES as GUIDANCE_MODES
from pcdiff_jax.model.guidance import GuidanceConfig


def _policy_item(text: str) -> tuple[str, object]:
  """'field=value' -> (field, value); a comma-separated value is a tuple."""
  name, sep, value = text.partition("=")
  if not sep or not name:
    raise argparse.ArgumentTypeError(f"expected FIELD=VALUE, got {text!r}")
  return name, tuple(value.split(",")) if "," in value else value


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.rollout", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", required=True, nargs="+",
                 help="TFRecord file(s) or glob(s) of WOMD motion tf.Examples or Scenario protos")
  p.add_argument("--method", default="cv", choices=sorted(evaluation.METHODS) + list(evaluation.LEARNED))
  p.add_argument("--checkpoint", default=None,
                 help="training workdir or model folder of the learned methods (pcdiff, pcdiff-noprior, "
                      "simpl-ar; simpl-ar reads its own encoder, simpl_ar/, where the folder has one)")
  p.add_argument("--ego", default="log", choices=evaluation.EGOS,
                 help="the SDC's fixed policy: log replay (default) or IDM")
  p.add_argument("--ddim-steps", type=int, default=5)
  p.add_argument("--replan-every", type=int, default=1, help="steps between plans (1 = 10 Hz)")
  p.add_argument("--consistent-noise", action="store_true",
                 help="draw each agent's initial DDIM noise once per rollout for its cold plans (default: at "
                      "every replan; warm-started replans always draw fresh noise)")
  p.add_argument("--execute", default="actions", choices=["actions", "track"],
                 help="pcdiff: run the plan's actions (paper) or track its path 0.5 s ahead (pure pursuit)")
  p.add_argument("--prior-centre", default="mean", choices=["mean", "top1"],
                 help="pcdiff: start DDIM around the mean of the K proposals (paper) or the most likely one")
  p.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=True,
                 help="pcdiff: start each replan from the previous plan, advanced by the executed steps "
                      "(amortised replanning; the default), or from the proposal prior (--no-warm-start)")
  p.add_argument("--warm-step", type=int, default=evaluation.EvalConfig.warm_step,
                 help="pcdiff --warm-start: the diffusion step the previous plan is noised to (of 100)")
  p.add_argument("--warm-ddim-steps", type=int, default=evaluation.EvalConfig.warm_ddim_steps,
                 help="pcdiff --warm-start: DDIM steps from --warm-step")
  p.add_argument("--ensemble-brake-weight", type=float, default=evaluation.EvalConfig.ensemble_brake_weight,
                 help="the temporal ensemble's acceleration weight where a new plan brakes harder than the "
                      "previous one (default: the same as --temporal-ensemble's)")
  p.add_argument("--ensemble-brake-margin", type=float, default=evaluation.EvalConfig.ensemble_brake_margin,
                 help="m/s^2: --ensemble-brake-weight applies where the new plan brakes harder by more than this")
  p.add_argument("--ensemble-pass", choices=("brake", "both"), default=evaluation.EvalConfig.ensemble_pass,
                 help="which disagreements over the margin take --ensemble-brake-weight: braking only, or either way")
  p.add_argument("--warm-proposals", type=int, default=evaluation.EvalConfig.warm_proposals,
                 help="pcdiff --warm-start with --select-samples S > 1: samples 1..N of a warm replan "
                      "start from each agent's N most likely proposals instead of its previous plan "
                      "(0 = off; at most S - 1)")
  p.add_argument("--jerk-limit", type=float, nargs=2, metavar=("RISE", "FALL"),
                 default=evaluation.EvalConfig.jerk_limit,
                 help="pcdiff: m/s^3 the executed acceleration may rise / fall per second from the "
                      "last step's (0: no limit on that side)")
  p.add_argument("--temporal-ensemble", type=float, nargs=2, metavar=("ACCEL", "YAW_RATE"),
                 default=evaluation.EvalConfig.temporal_ensemble,
                 help="pcdiff: weights in [0, 1) of the earlier plans in the executed plan, per action "
                      "channel (exponential temporal ensembling: smooths the executed actions; 0 = off)")
  p.add_argument("--select-samples", type=int, default=evaluation.EvalConfig.select_samples,
                 help="pcdiff: draw this many joint plans per replan and keep, per agent, the one whose "
                      "plan overlaps the others' least over 3 s (1 = off; S times the denoiser's work)")
  p.add_argument("--select-map-weight", type=float, default=evaluation.EvalConfig.select_map_weight,
                 help="pcdiff with --select-samples > 1: also prefer the sample that stays on the road, "
                      "with this weight on its J_map (m^2; 0 = off; builds a road field per scenario)")
  p.add_argument("--select-stride", type=int, default=evaluation.EvalConfig.select_stride,
                 help="pcdiff with --select-samples > 1: score the samples' overlaps and J_map at every "
                      "N-th step of the 3 s lookahead (cheaper; 1 = every step)")
  p.add_argument("--select-neighbours", type=int, default=evaluation.EvalConfig.select_neighbours,
                 help="pcdiff with --select-samples > 1: check each agent's samples for overlaps against "
                      "its N nearest agents' only (a bounding-circle broad phase; 0 = every pair)")
  p.add_argument("--select-proposal-weight", type=float,
                 default=evaluation.EvalConfig.select_proposal_weight,
                 help="pcdiff with --select-samples > 1: also prefer the sample the encoder's proposals "
                      "make likeliest, with this weight on its negative log-likelihood (nats; 0 = off)")
  p.add_argument("--select-proposal-scale", type=float,
                 default=evaluation.EvalConfig.select_proposal_scale,
                 help="the likelihood's scale around each proposal (m)")
  p.add_argument("--stop-hold", action=argparse.BooleanOptionalAction,
                 default=evaluation.EvalConfig.stop_hold,
                 help="pcdiff: braking stops a forward-moving agent at standstill instead of backing it up")
  p.add_argument("--start-gate", type=float, nargs=2, metavar=("SECONDS", "METRES"),
                 default=evaluation.EvalConfig.start_gate,
                 help="pcdiff: a (nearly) stopped agent starts only when its plan carries it at least "
                      "METRES within SECONDS (0 0 = off)")
  p.add_argument("--policy", nargs="+", default=[], metavar="FIELD=VALUE", type=_policy_item,
                 help="pcdiff: set any `policy.PolicyConfig` field, e.g. --policy max_curvature=0.3 "
                      "jerk_limit=1.5,5 (tuples comma-separated)")
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
  for name in ("num_steps", "max_agents", "batch_size", "ddim_steps", "replan_every", "num_rollouts",
               "seeds", "select_samples", "select_stride"):
    if getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if args.select_map_weight < 0:
    p.error("--select-map-weight must be >= 0")
  if args.select_neighbours < 0:
    p.error("--select-neighbours must be >= 0 (0: every pair)")
  if args.select_proposal_weight < 0:
    p.error("--select-proposal-weight must be >= 0")
  if args.select_proposal_scale <= 0:
    p.error("--select-proposal-scale must be > 0 (m)")
  if not all(g >= 0 for g in args.start_gate):
    p.error("--start-gate takes SECONDS METRES >= 0")
  lookahead = PolicyConfig.select_lookahead
  if args.select_stride > lookahead:
    p.error(f"--select-stride must be <= {lookahead} (the selection's lookahead, in steps)")
  if not 0 <= args.warm_step <= 99:
    p.error("--warm-step must be in [0, 99]")
  if not all(0.0 <= m < 1.0 for m in args.temporal_ensemble):
    p.error("--temporal-ensemble weights must be in [0, 1)")
  if args.ensemble_brake_weight is not None and not 0.0 <= args.ensemble_brake_weight < 1.0:
    p.error("--ensemble-brake-weight must be in [0, 1)")
  if not all(j >= 0.0 for j in args.jerk_limit):
    p.error("--jerk-limit values must be >= 0 (m/s^3)")
  if not 1 <= args.warm_ddim_steps <= args.warm_step + 1:
    p.error("--warm-ddim-steps must be in [1, --warm-step + 1]")
  if not 0 <= args.warm_proposals <= args.select_samples - 1:
    p.error("--warm-proposals must be in [0, --select-samples - 1]")
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
  try:
    with_overrides(PolicyConfig(), args.policy)
  except (ValueError, TypeError) as err:
    p.error(f"--policy: {err}")
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  _args.setup_logging()
  cfg = evaluation.EvalConfig(method=args.method, checkpoint=args.checkpoint, ego=args.ego,
                              ddim_steps=args.ddim_steps, consistent_noise=args.consistent_noise,
                              execute=args.execute, prior_centre=args.prior_centre,
                              replan_every=args.replan_every, num_rollouts=args.num_rollouts,
                              seeds=args.seeds,
                              num_steps=args.num_steps, batch_size=args.batch_size,
                              gifs=args.gifs, seed=args.seed, score_adversary=args.score_adversary,
                              max_scenarios=args.max_scenarios, warm_start=args.warm_start,
                              warm_step=args.warm_step, warm_ddim_steps=args.warm_ddim_steps,
                              temporal_ensemble=tuple(args.temporal_ensemble),
                              jerk_limit=tuple(args.jerk_limit), warm_proposals=args.warm_proposals,
                              ensemble_brake_weight=args.ensemble_brake_weight,
                              ensemble_brake_margin=args.ensemble_brake_margin,
                              ensemble_pass=args.ensemble_pass,
                              simpl_ar_sample=args.simpl_ar_sample, select_samples=args.select_samples,
                              select_map_weight=args.select_map_weight, select_stride=args.select_stride,
                              select_neighbours=args.select_neighbours,
                              select_proposal_weight=args.select_proposal_weight,
                              select_proposal_scale=args.select_proposal_scale,
                              stop_hold=args.stop_hold,
                              start_gate=tuple(args.start_gate),
                              policy_overrides=tuple(args.policy),
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
