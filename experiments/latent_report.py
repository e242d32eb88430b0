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
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys

from experiments import _args, _report


def parse_args(argv=None):
  p = argparse.ArgumentParser(prog="python -m experiments.latent_report", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--workdir", required=True, help="holds the trained encoder (WORKDIR/encoder)")
  p.add_argument("--data", required=True, nargs="+")
  p.add_argument("--val-data", required=True, nargs="+")
  p.add_argument("--dims", type=int, nargs="+", default=[8, 16, 32, 64])
  p.add_argument("--out", required=True, type=_args.output_dir)
  return p.parse_args(argv)


def main(argv=None) -> int:
  args = parse_args(argv)
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
