"""The same scenes under nominal, objective and adversarial guidance (the paper's Fig. 3).

  python -m experiments.guidance_figure --scenarios data/synth/val-00000-of-00001.tfrecord \
      --checkpoint runs/cpu --num-scenes 3 --out runs/fig3

Rolls ours out in closed loop (80 steps, replanning every 10 steps by default)
on the first N scenes once per
guidance mode with the same seed, and writes OUT/fig3.png (rows: scenes;
columns: modes; each row drawn at the step where the adversarial run's
pursuer comes closest to the SDC, with trails from the start; the SDC red, the
pursuer traced in orange and ringed in every column) and
OUT/gifs/<mode>_<scenario>.gif.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import jax
import numpy as np

from experiments import _args

MODES = ("none", "objective", "adversarial")
TITLES = {"none": "nominal", "objective": "objective guidance", "adversarial": "adversarial (IBR)"}


def parse_args(argv=None) -> argparse.Namespace:
  from pcdiff_jax.model.guidance import GuidanceConfig
  p = argparse.ArgumentParser(prog="python -m experiments.guidance_figure", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", required=True, help="a WOMD-format TFRecord (or glob)")
  p.add_argument("--checkpoint", required=True, help="training workdir of ours")
  p.add_argument("--num-scenes", type=int, default=3)
  p.add_argument("--ddim-steps", type=int, default=5)
  p.add_argument("--replan-every", type=int, default=10,
                 help="steps between plans (guided plans cost several gradient passes on CPU)")
  p.add_argument("--w-map", type=float, default=None,
                 help="weight of J_map (default: 100 for objective guidance, 1 for adversarial)")
  p.add_argument("--w-coll", type=float, default=None,
                 help="weight of J_coll (default: 10 for objective guidance, 1 for adversarial)")
  p.add_argument("--w-pursue", type=float, default=30.0)
  p.add_argument("--eta", type=float, default=0.07)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--out", required=True, type=_args.output_dir)
  args = p.parse_args(argv)
  if min(args.num_scenes, args.ddim_steps, args.replan_every) < 1:
    p.error("--num-scenes, --ddim-steps and --replan-every must be >= 1")
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  from pcdiff_jax import evaluation, viz
  from pcdiff_jax.data import womd
  from pcdiff_jax.model.guidance import GuidanceConfig
  from pcdiff_jax.policy import PolicyConfig
  try:
    states, meta = next(iter(womd.iterate(args.scenarios, batch_size=args.num_scenes, with_meta=True)))
  except (FileNotFoundError, ValueError, StopIteration) as err:
    print(f"error: cannot read {args.scenarios}: {err}", file=sys.stderr)
    return 2
  n = states.shape[0]
  rngs = jax.random.split(jax.random.PRNGKey(args.seed), n)
  base = GuidanceConfig(w_map=args.w_map, w_coll=args.w_coll, w_pursue=args.w_pursue, eta=args.eta)
  finals = {}
  for mode in MODES:
    cfg = evaluation.EvalConfig(method="pcdiff", checkpoint=args.checkpoint,
                                policy=PolicyConfig(ddim_steps=args.ddim_steps, replan_every=args.replan_every),
                                guidance=dataclasses.replace(base, mode=mode))
    try:
      actor, params = evaluation.make_actor(cfg)
    except (FileNotFoundError, ValueError) as err:
      print(f"error: {err}", file=sys.stderr)
      return 2
    print(f"rolling out {n} scene(s) with guidance {mode} ...", flush=True)
    finals[mode] = jax.device_get(evaluation.make_rollout_fn(actor, cfg)(states, rngs, params))
  start = cfg.init_steps - 1
  pursuers = np.asarray(jax.vmap(lambda f: evaluation.pursuer_at_start(f, cfg))(finals["adversarial"]))
  os.makedirs(os.path.join(args.out, "gifs"), exist_ok=True)
  fig = viz._figure((4.0 * len(MODES), 4.0 * n), 90)
  axes = fig.subplots(n, len(MODES), squeeze=False)
  for i in range(n):
    k = int(pursuers[i])
    moment = _closest_approach(jax.tree_util.tree_map(lambda a: np.asarray(a[i]), finals["adversarial"]), k, start)
    for j, mode in enumerate(MODES):
      one = jax.tree_util.tree_map(lambda a: np.asarray(a[i]), finals[mode])
      ax = viz.plot_scene(axes[i, j], one, timestep=moment, trail=moment - start, view_radius=50.0,
                          title=f"{meta.scenario_id[i][:10]} t={(moment - start) / 10:.1f}s: {TITLES[mode]}")
      if k >= 0:   # the pursuer of the adversarial run, ringed in every column for comparison
        traj = one.sim_trajectory
        seen = np.flatnonzero(traj.valid[k, start:moment + 1]) + start
        if len(seen):
          ax.plot(traj.x[k, seen], traj.y[k, seen], color="tab:orange", lw=1.0)
          ax.scatter([traj.x[k, seen[-1]]], [traj.y[k, seen[-1]]], s=160, facecolors="none",
                     edgecolors="tab:orange", linewidths=2.0, zorder=5)
      viz.render_rollout_gif(one, os.path.join(args.out, "gifs", f"{mode}_{meta.scenario_id[i]}.gif"))
  fig.tight_layout()
  path = os.path.join(args.out, "fig3.png")
  fig.savefig(path)
  print(f"wrote {path} and {args.out}/gifs/")
  return 0


def _closest_approach(state, pursuer: int, start: int) -> int:
  """The step of the adversarial run where the pursuer comes closest to the SDC
  (the last step without a pursuer)."""
  traj = state.sim_trajectory
  last = traj.num_timesteps - 1
  if pursuer < 0:
    return last
  sdc = int(np.argmax(state.object_metadata.is_sdc))
  both = traj.valid[sdc] & traj.valid[pursuer]
  dist = np.hypot(traj.x[sdc] - traj.x[pursuer], traj.y[sdc] - traj.y[pursuer])
  dist = np.where(both & (np.arange(last + 1) > start), dist, np.inf)
  return int(np.argmin(dist)) if np.isfinite(dist).any() else last


if __name__ == "__main__":
  sys.exit(main())
