"""The same scenes under nominal, objective and adversarial guidance (the paper's Fig. 3).

  python -m experiments.guidance_figure --scenarios data/synth/val-00000-of-00001.tfrecord \
      --checkpoint runs/cpu --num-scenes 3 --out runs/fig3

Rolls ours out in closed loop (80 steps, replanning every 10 steps by default)
on the first N scenes once per
guidance mode with the same seed, and writes OUT/fig3.png (rows: scenes;
columns: modes; each panel the last step with 8 s trails; the SDC red, the
pursuer of the adversarial run ringed and traced in orange in every column) and
OUT/gifs/<mode>_<scenario>.gif.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import jax
import numpy as np

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
  p.add_argument("--w-map", type=float, default=GuidanceConfig.w_map)
  p.add_argument("--w-coll", type=float, default=GuidanceConfig.w_coll)
  p.add_argument("--w-pursue", type=float, default=30.0)
  p.add_argument("--eta", type=float, default=0.07)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--out", required=True)
  args = p.parse_args(argv)
  if min(args.num_scenes, args.ddim_steps, args.replan_every) < 1:
    p.error("--num-scenes, --ddim-steps and --replan-every must be >= 1")
  return args


def main(argv=None) -> int:
  args = parse_args(argv)
  from pcdiff_jax import evaluation, viz
  from pcdiff_jax.data import womd
  from pcdiff_jax.model.guidance import GuidanceConfig
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
    cfg = evaluation.EvalConfig(method="pcdiff", checkpoint=args.checkpoint, ddim_steps=args.ddim_steps,
                                replan_every=args.replan_every,
                                guidance=dataclasses.replace(base, mode=mode))
    try:
      actor, params = evaluation.make_actor(cfg)
    except (FileNotFoundError, ValueError) as err:
      print(f"error: {err}", file=sys.stderr)
      return 2
    print(f"rolling out {n} scene(s) with guidance {mode} ...", flush=True)
    finals[mode] = jax.device_get(evaluation.make_rollout_fn(actor, cfg)(states, rngs, params))
  pursuers = np.asarray(jax.vmap(lambda f: evaluation.pursuer_at_start(f, cfg))(finals["adversarial"]))
  os.makedirs(os.path.join(args.out, "gifs"), exist_ok=True)
  fig = viz._figure((4.0 * len(MODES), 4.0 * n), 90)
  axes = fig.subplots(n, len(MODES), squeeze=False)
  for i in range(n):
    for j, mode in enumerate(MODES):
      one = jax.tree_util.tree_map(lambda a: np.asarray(a[i]), finals[mode])
      last = one.sim_trajectory.num_timesteps - 1
      ax = viz.plot_scene(axes[i, j], one, timestep=last, trail=80, view_radius=50.0,
                          title=f"{meta.scenario_id[i][:10]}: {TITLES[mode]}")
      k = int(pursuers[i])
      if k >= 0:   # the pursuer of the adversarial run, ringed in every column for comparison
        traj = one.sim_trajectory
        ax.plot(traj.x[k, 10:], traj.y[k, 10:], color="tab:orange", lw=1.0)
        ax.scatter([traj.x[k, last]], [traj.y[k, last]], s=160, facecolors="none",
                   edgecolors="tab:orange", linewidths=2.0, zorder=5)
      viz.render_rollout_gif(one, os.path.join(args.out, "gifs", f"{mode}_{meta.scenario_id[i]}.gif"))
  fig.tight_layout()
  path = os.path.join(args.out, "fig3.png")
  fig.savefig(path)
  print(f"wrote {path} and {args.out}/gifs/")
  return 0


if __name__ == "__main__":
  sys.exit(main())
