"""Reconstruction error of the PCA action latent for several dimensions d.

  python -m experiments.latent_report --workdir runs/cpu --data 'data/synth/train-*' \
      --val-data 'data/synth/val-*' --dims 8 16 32 64 --out runs/cpu/latent

For each d, fits the latent as stage 2 does (logged futures + the trained
encoder's proposals of the first `pca_fit_scenes` training scenes), then
takes the logged futures of the val agents valid over the whole 8 s:
actions (inverse dynamics) -> encode -> decode -> rollout with f, and reports
the position error at 8 s and its mean over the horizon (m), with the share
of variance the d components explain. "inverse only" is the error of the
inverse dynamics itself (no latent). Writes OUT/latent.json and OUT/latent.md.

With --checkpoint instead of --workdir and --data, it reports the stage-2
targets of that model's latent on --val-data (agents valid over the 8 s at
t = 10, movers and still ones apart): for each --fit-sigma, the position
error of the target's rollout and its whitened RMS (1 = the latent's
training spread); 0 is the projection, sigma > 0 `latent.fit_to_path`:

  python -m experiments.latent_report --checkpoint checkpoints/pcdiff-cpu-v8 \
      --val-data ../shared/data/womd_real/val.scenario.tfrecord --fit-sigma 0 1 3 --out OUT
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import sys

from experiments import _args, _report


def parse_args(argv=None):
  p = argparse.ArgumentParser(prog="python -m experiments.latent_report", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--workdir", help="holds the trained encoder (WORKDIR/encoder)")
  p.add_argument("--data", nargs="+")
  p.add_argument("--checkpoint", help="a trained model: report its stage-2 targets instead")
  p.add_argument("--val-data", required=True, nargs="+")
  p.add_argument("--dims", type=int, nargs="+", default=[8, 16, 32, 64])
  p.add_argument("--fit-sigma", type=float, nargs="+", default=[0.0, 1.0],
                 help="with --checkpoint: target fit tolerances (m), 0 = the projection")
  p.add_argument("--max-rms", type=float, default=3.0,
                 help="with --checkpoint: also the share of agents whose target is above this whitened RMS")
  p.add_argument("--out", required=True, type=_args.output_dir)
  args = p.parse_args(argv)
  if args.checkpoint is None and (args.workdir is None or args.data is None):
    p.error("give --workdir and --data (latent fit), or --checkpoint (its targets)")
  if any(s < 0 for s in args.fit_sigma):
    p.error("--fit-sigma must be >= 0")
  return args


def target_report(args) -> int:
  """The stage-2 targets of a trained model's latent on --val-data (see the module doc)."""
  import jax
  import jax.numpy as jnp
  import numpy as np

  from pcdiff_jax import shipped
  from pcdiff_jax.model import latent, planner
  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import diffusion_stage, encoder_stage
  try:
    models, cfg = shipped.pretrained(path=args.checkpoint)
    spec = dataclasses.replace(encoder_stage.cache_spec(cfg), current_steps=(10,))
    val, _ = data_lib.load_or_build(args.val_data, spec, os.path.join(args.out, "cache"), "val")
  except (FileNotFoundError, ValueError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  @functools.partial(jax.jit, static_argnums=1)
  def sums(batch, sigma):
    speed = planner.agent_speed(batch.feats)
    y, full = diffusion_stage.latent_targets(batch, models.stats, speed, dataclasses.replace(
        cfg, diffusion=dataclasses.replace(cfg.diffusion, target_fit_sigma=sigma)))
    t = batch.targets
    dist = jnp.linalg.norm(latent.rollout(y, speed, models.stats, cfg.kinematics)[..., :2] - t.future_xy, axis=-1)
    rms = latent.whitened_rms(y, models.stats)
    path = jnp.sum(jnp.linalg.norm(jnp.diff(t.future_xy, axis=-2), axis=-1), -1)
    out = []
    for group in (full & (path > 1), full & (path <= 1)):
      total = lambda v: jnp.sum(jnp.where(group, v, 0.0))
      out.append(jnp.stack([total(dist.mean(-1)), total(dist[..., -1]), total(rms),
                            total((rms > args.max_rms).astype(jnp.float32)), jnp.sum(group)]))
    return jnp.stack(out)

  rows = []
  for sigma in args.fit_sigma:
    total = np.zeros((2, 5))
    for batch, mask in data_lib.eval_batches(val, 8):
      batch = batch.replace(targets=batch.targets.replace(
          future_valid=batch.targets.future_valid & mask[:, None, None]))
      total += np.asarray(sums(jax.tree_util.tree_map(jnp.asarray, batch), sigma))
    for name, (ade, fde, rms, over, n) in zip(("movers", "still"), total):
      n = max(n, 1)
      rows.append({"fit_sigma": sigma, "agents": name, "count": int(n), "ade": ade / n, "fde_8s": fde / n,
                   "whitened_rms": rms / n, "over_max_rms": over / n})
      print(rows[-1], flush=True)
  lines = ["| target | agents | count | mean error (m) | error at 8 s (m) | whitened RMS | "
           f"share above {args.max_rms:g} |", "|---|---|---|---|---|---|---|"]
  lines += [f"| {'projection' if r['fit_sigma'] == 0 else 'fit, sigma %g m' % r['fit_sigma']} | {r['agents']} | "
            f"{r['count']} | {r['ade']:.2f} | {r['fde_8s']:.2f} | {r['whitened_rms']:.2f} | "
            f"{100 * r['over_max_rms']:.1f}% |" for r in rows]
  table = "\n".join(lines) + (f"\n\n{args.checkpoint}'s latent; agents valid over the 8 s from t = 10 "
                               "(movers: more than 1 m of path).\n")
  _report.write(args.out, "latent_targets", rows, table)
  return 0


def main(argv=None) -> int:
  args = parse_args(argv)
  if args.checkpoint is not None:
    return target_report(args)
  import jax
  import jax.numpy as jnp
  import numpy as np

  from pcdiff_jax.model import latent, planner
  from pcdiff_jax.sim import dynamics
  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import diffusion_stage, encoder_stage
  try:
    enc, cfg = encoder_stage.load(args.workdir)
    cache = os.path.join(args.workdir, "cache")
    spec = dataclasses.replace(encoder_stage.cache_spec(cfg), current_steps=(10,))
    train, _ = data_lib.load_or_build(args.data, spec, cache, "train")
    val, _ = data_lib.load_or_build(args.val_data, spec, cache, "val")
  except (FileNotFoundError, ValueError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2

  @jax.jit
  def errors(stats, batch):
    actions, full = diffusion_stage.logged_actions(batch, cfg)
    speed = planner.agent_speed(batch.feats)
    direct = latent.initial_states(speed)[..., None, :]
    inv = dynamics.rollout(direct[..., 0, :], actions, cfg.kinematics.dt)
    rec = latent.rollout(latent.encode(actions, stats), speed, stats, cfg.kinematics)
    d_rec = jnp.linalg.norm(rec[..., :2] - batch.targets.future_xy, axis=-1)
    d_inv = jnp.linalg.norm(inv[..., :2] - batch.targets.future_xy, axis=-1)
    total = lambda v: jnp.sum(jnp.where(full, v, 0.0))
    return jnp.stack([total(d_rec[..., -1]), total(d_rec.mean(-1)), total(d_inv[..., -1]),
                      total(d_inv.mean(-1)), jnp.sum(full)])

  rows = []
  for dim in args.dims:
    stats = diffusion_stage.fit_latent(enc, cfg, train, cfg.diffusion.pca_fit_scenes, dim=dim)
    sums = np.zeros(5)
    for batch, mask in data_lib.eval_batches(val, 8):
      batch = batch.replace(targets=batch.targets.replace(
          future_valid=batch.targets.future_valid & mask[:, None, None]))
      sums += np.asarray(errors(stats, jax.tree_util.tree_map(jnp.asarray, batch)))
    n = max(sums[4], 1)
    rows.append({"dim": dim, "fde_8s": sums[0] / n, "ade": sums[1] / n, "inverse_fde_8s": sums[2] / n,
                 "inverse_ade": sums[3] / n, "explained": float(jnp.sum(stats.explained)),
                 "agents": int(sums[4])})
    print(rows[-1], flush=True)
  lines = ["| d | error at 8 s (m) | mean error (m) | variance explained |", "|---|---|---|---|"]
  lines += [f"| {r['dim']} | {r['fde_8s']:.3f} | {r['ade']:.3f} | {r['explained']:.4f} |" for r in rows]
  lines.append(f"| inverse only (no latent) | {rows[0]['inverse_fde_8s']:.3f} | "
               f"{rows[0]['inverse_ade']:.3f} | |")
  table = "\n".join(lines) + f"\n\n{rows[0]['agents']} val agents valid over the 8 s horizon.\n"
  _report.write(args.out, "latent", rows, table)
  return 0


if __name__ == "__main__":
  sys.exit(main())
