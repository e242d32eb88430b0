"""Stage 2: fit the PCA action latent, train the joint denoiser, load it back.

Needs a trained stage-1 encoder in WORKDIR/encoder (frozen). `train`:

1. fits the latent (`model.latent.fit`) on the first `pca_fit_scenes`
   training examples: the logged futures of agents valid over the whole
   horizon, their recovery futures (`training.perturb`) and, with
   `diffusion.pca_proposal_weight`, the K proposals of every valid agent;
2. trains the denoiser with loss = w_diff * mean ||n_hat - sigma eps||^2 +
   w_state * SmoothL1 on (x, y, psi) of the rollout of the decoded one-step
   estimate y0_hat, both over agents with a fully valid future (the others
   stay in the scene, at their proposal mean, and are not scored);
3. saves the encoder parameters and the latent statistics with every
   checkpoint (`TrainState.extra`), so WORKDIR/diffusion is self-contained.

Validation: the loss at fixed noise, and the open-loop minADE / minFDE of N
sampled joint plans (DDIM, the config's steps) against the log, with the
fraction of sampled scenes where two agents' boxes overlap.
"""
from __future__ import annotations

import os
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh

from pcdiff_jax import config as config_lib
from pcdiff_jax import distributed
from pcdiff_jax.config import Config
from pcdiff_jax.model import denoiser as denoiser_lib
from pcdiff_jax.model import diffusion, encoder, latent, planner
from pcdiff_jax.model.planner import Conditioning, Models
from pcdiff_jax.sim import geometry
from pcdiff_jax.training import data as data_lib
from pcdiff_jax.training import encoder_stage, perturb, trainer
from pcdiff_jax.training.data import Example



def stage_dir(use_prior: bool) -> str:
  """WORKDIR sub-folder of a variant: both share the stage-1 encoder beside them."""
  return "diffusion" if use_prior else "diffusion_noprior"

CONFIG_SECTIONS = ("features", "encoder", "kinematics", "diffusion", "diffusion_train")


def logged_actions(batch: Example, cfg: Config) -> tuple[jax.Array, jax.Array]:
  """Actions of the logged futures (..., A, T, 2) and which agents are fully valid (..., A)."""
  t = batch.targets
  speed = planner.agent_speed(batch.feats)
  actions, _ = latent.actions_from_future(t.future_xy, t.future_yaw, t.future_speed,
                                          t.future_valid, speed, cfg.kinematics)
  full = batch.feats.agent_valid & jnp.all(t.future_valid, -1)
  return actions, full


def latent_targets(batch: Example, stats: latent.LatentStats, speed: jax.Array,
                   cfg: Config) -> tuple[jax.Array, jax.Array]:
  """Latent targets of the logged futures (..., A, d) and which agents are
  trained on (..., A: fully valid). The projection of the inverse actions, or
  with `diffusion.target_fit_sigma` > 0 the latent fitted to the logged
  positions from there (`latent.fit_to_path`), then without the agents whose
  fit stays out of distribution (`diffusion.target_max_rms`; RESULTS, "Latent
  targets of real logs")."""
  actions, full = logged_actions(batch, cfg)
  y0 = latent.encode(actions, stats)
  d = cfg.diffusion
  if d.target_fit_sigma > 0:
    t = batch.targets
    y0 = jax.lax.stop_gradient(latent.fit_to_path(y0, t.future_xy, t.future_valid, speed, stats,
                                                  cfg.kinematics, d.target_fit_sigma))
    if d.target_max_rms > 0:
      full = full & (latent.whitened_rms(y0, stats) <= d.target_max_rms)
  return y0, full


# ----------------------------------------------------------------------------
# Latent fit.


def fit_latent(encoder_params: Any, cfg: Config, examples: Example, num_scenes: int,
               batch_size: int = 8, dim: Optional[int] = None) -> latent.LatentStats:
  """PCA latent of the first `num_scenes` examples: their logged futures, the
  recovery futures that `diffusion_train.perturb` trains on (drawn with a
  fixed key), and the K proposals with `diffusion.pca_proposal_weight` of the
  total weight."""
  pcfg = cfg.diffusion_train.perturb

  @jax.jit
  def collect(batch: Example, rng):
    actions, full = logged_actions(batch, cfg)
    moved = perturb.perturb(batch, rng, pcfg, cfg.kinematics.dt)
    moved_actions, moved_full = logged_actions(moved, cfg)
    out = encoder.apply(encoder_params, batch.feats, cfg.encoder)
    props = latent.actions_from_positions(out.trajectories, planner.agent_speed(batch.feats)[..., None],
                                          cfg.kinematics)                       # (B, A, K, T, 2)
    changed = jnp.any(moved.feats.agent_center != batch.feats.agent_center, -1)   # (B, A)
    return actions, full, moved_actions, moved_full & changed, props, batch.feats.agent_valid

  logs, props = [], []
  sub = jax.tree_util.tree_map(lambda a: a[:num_scenes], examples)
  for i, (batch, mask) in enumerate(data_lib.eval_batches(sub, batch_size)):
    a, full, ma, mfull, p, valid = jax.device_get(collect(batch, jax.random.key(i)))
    logs += [a[full & mask[:, None]], ma[mfull & mask[:, None]]]
    props.append(p[valid & mask[:, None]].reshape((-1,) + p.shape[-2:]))
  logs, props = np.concatenate(logs), np.concatenate(props)
  if not len(logs):
    raise ValueError("no agent with a fully valid future in the latent fit scenes")
  # Proposals outnumber logs K to 1, and the mean of their modes is not a
  # mode: fitted half on proposals, the PCA mean started with a right turn
  # (docs/RESULTS.md), so by default the latent is fitted on futures only.
  w_prop = cfg.diffusion.pca_proposal_weight
  if w_prop <= 0.0:
    return latent.fit(logs, cfg.diffusion.latent_dim if dim is None else dim)
  weights = np.concatenate([np.full(len(logs), (1 - w_prop) / len(logs)),
                            np.full(len(props), w_prop / len(props))])
  return latent.fit(np.concatenate([logs, props]), cfg.diffusion.latent_dim if dim is None else dim,
                    weights=weights)


# ----------------------------------------------------------------------------
# Loss.


def _noised(params, cond: Conditioning, y0, rng, cfg: Config, dropout_rng=None):
  sched = planner.schedule_of(cfg)
  k_s, k_eps = jax.random.split(rng)
  batch = y0.shape[0]
  s = jax.random.randint(k_s, (batch,), 0, sched.num_steps)
  eps = jax.random.normal(k_eps, y0.shape)
  y_s = diffusion.q_sample(y0, s[:, None], eps, cond.sigma, sched)
  pred = denoiser_lib.apply(params, y_s, s, cond.inputs, cfg.diffusion.denoiser, rng=dropout_rng,
                            anchor=cond.anchor)
  y0_hat = diffusion.predict_y0(y_s, s[:, None], pred, sched)
  return pred, cond.sigma * eps, y0_hat


def diffusion_loss(params, extra, batch: Example, rng, cfg: Config):
  """(loss, metrics) for a batch (B, ...). extra = {"encoder", "stats"}."""
  stats = extra["stats"]
  cond = planner.condition(extra["encoder"], stats, batch.feats, cfg)
  y0, full = latent_targets(batch, stats, cond.speed, cfg)
  y0 = jnp.where(full[..., None], y0, cond.mu)
  if cfg.diffusion.denoiser.anchor_inputs:   # the mode the logged future took
    cond = planner.with_anchor(cond, planner.nearest_proposal(cond, y0))
  k_noise, k_drop = jax.random.split(rng)
  pred, target, y0_hat = _noised(params, cond, y0, k_noise, cfg, dropout_rng=k_drop)
  n = jnp.maximum(jnp.sum(full), 1)
  l_diff = jnp.sum(jnp.where(full[..., None], (pred - target) ** 2, 0.0)) / (n * y0.shape[-1])
  states = latent.rollout(y0_hat, cond.speed, stats, cfg.kinematics)          # (B, A, T, 4)
  t = batch.targets
  err = jnp.concatenate([states[..., :2] - t.future_xy,
                         geometry.wrap_angle(states[..., 2] - t.future_yaw)[..., None]], -1)
  huber = optax.huber_loss(err, delta=1.0).sum(-1).mean(-1)                   # (B, A)
  l_state = jnp.sum(jnp.where(full, huber, 0.0)) / n
  d = cfg.diffusion
  loss = d.diffusion_loss_weight * l_diff + d.state_loss_weight * l_state
  return loss, {"loss": loss, "diffusion": l_diff, "state": l_state}


# ----------------------------------------------------------------------------
# Validation.


def open_loop_metrics(states: jax.Array, batch: Example, cfg: Config) -> dict:
  """Sums over scored agents of N sampled plans states (N, B, A, T, 4)."""
  t = batch.targets
  full = batch.feats.agent_valid & jnp.all(t.future_valid, -1)                # (B, A)
  dist = jnp.linalg.norm(states[..., :2] - t.future_xy, axis=-1)              # (N, B, A, T)
  ade, fde = dist.mean(-1), dist[..., -1]
  overlap = jax.vmap(lambda s: planner.scene_overlap(s, batch.feats))(states)  # (N, B)
  scene = jnp.any(full, -1)
  total = lambda v: jnp.sum(jnp.where(full, v, 0.0))
  return {"count": jnp.sum(full).astype(jnp.float32),
          "min_ade": total(ade.min(0)), "min_fde": total(fde.min(0)),
          "mean_ade": total(ade.mean(0)),
          "scenes": jnp.sum(scene).astype(jnp.float32),
          "overlap_scenes": jnp.sum(jnp.where(scene[None], overlap, False)) / states.shape[0]}


def make_evaluate(cfg: Config, examples: Example, batch_size: int, num_samples: int = 6,
                  ddim_steps: Optional[int] = None, prior_init: bool = True, seed: int = 0):
  """(params, extra) -> validation metrics (loss, min_ade, min_fde, overlap rate)."""
  @jax.jit
  def sums(params, extra, batch: Example, mask, rng):
    batch = batch.replace(targets=batch.targets.replace(
        future_valid=batch.targets.future_valid & mask[:, None, None]))
    loss, parts = diffusion_loss(params, extra, batch, rng, cfg)
    cond = planner.condition(extra["encoder"], extra["stats"], batch.feats, cfg)
    keys = jax.random.split(jax.random.fold_in(rng, 1), num_samples)
    y0 = jax.vmap(lambda k: planner.sample(params, cond, cfg, k, ddim_steps,
                                           prior_init=prior_init))(keys)       # (N, B, A, d)
    states = planner.decode_states(extra["stats"], cond, y0, cfg)
    out = open_loop_metrics(states, batch, cfg)
    out.update({f"loss_{k}": v * jnp.sum(mask) for k, v in parts.items()}, batches=jnp.sum(mask))
    return out

  def evaluate(params, extra) -> dict:
    total = None
    for i, (batch, mask) in enumerate(data_lib.eval_batches(examples, batch_size)):
      s = jax.device_get(sums(params, extra, batch, mask, jax.random.key(seed + i)))
      total = s if total is None else jax.tree_util.tree_map(np.add, total, s)
    count = max(float(total["count"]), 1.0)
    out = {k: float(total[k]) / count for k in ("min_ade", "min_fde", "mean_ade")}
    out["overlap_rate"] = float(total["overlap_scenes"]) / max(float(total["scenes"]), 1.0)
    out.update({k: float(v) / max(float(total["batches"]), 1.0)
                for k, v in total.items() if k.startswith("loss_")})
    out["count"] = float(total["count"])
    return out
  return evaluate


# ----------------------------------------------------------------------------
# Train / load.


def full_future_examples(examples: Example) -> Example:
  """Only examples with at least one fully valid future (t = 10 scenes, not t = 30)."""
  keep = np.asarray(np.any(examples.feats.agent_valid & examples.targets.future_valid.all(-1), -1))
  return jax.tree_util.tree_map(lambda a: a[keep], examples)


def train(cfg: Config, train_examples: Example, val_examples: Optional[Example], workdir: str,
          max_minutes: Optional[float] = None, progress: bool = True, mesh: Optional[Mesh] = None):
  """Trains (or resumes) stage 2 in WORKDIR/diffusion. Returns (state, val metrics).

  mesh: data-parallel over its devices (`pcdiff_jax.distributed`); then
  `train_examples` are this host's and it feeds its share of each global batch
  (the latent is fitted on each host's examples and process 0's fit is kept).
  """
  tc = cfg.diffusion_train
  folder = os.path.join(workdir, stage_dir(cfg.diffusion.denoiser.use_prior))
  enc_params, _ = encoder_stage.load(workdir)
  train_examples = full_future_examples(train_examples)
  ckpt = trainer.Checkpointer(folder, tc.keep_checkpoints)
  resuming = ckpt.latest_step() is not None
  ckpt.close()
  if resuming:   # the saved statistics are restored with the state: a template suffices
    stats = latent.placeholder(cfg.encoder.horizon, cfg.diffusion.latent_dim)
  else:
    stats = fit_latent(enc_params, cfg, train_examples, cfg.diffusion.pca_fit_scenes)
    print(f"latent: d={stats.dim}, explained variance {float(jnp.sum(stats.explained)):.4f}")
  extra = {"encoder": enc_params, "stats": stats}
  first = jax.tree_util.tree_map(lambda a: jnp.asarray(a[:1]), train_examples)
  cond = planner.condition(enc_params, stats, first.feats, cfg)
  one = jax.tree_util.tree_map(lambda a: a[0], cond.inputs)
  params = denoiser_lib.init(jax.random.key(tc.seed), cond.mu[0], jnp.zeros((), jnp.int32), one,
                             cfg.diffusion.denoiser)
  tx = trainer.make_optimizer(tc)
  state = trainer.create_state(params, tx, tc.seed, extra=extra)
  def loss_fn(params, extra, batch, rng):
    rng, k_perturb = jax.random.split(rng)
    batch = perturb.perturb(batch, k_perturb, tc.perturb, cfg.kinematics.dt)
    return diffusion_loss(params, extra, batch, rng, cfg)
  step_fn = trainer.make_train_step(loss_fn, tx, with_extra=True, mesh=mesh)
  evaluate = None
  if val_examples is not None:
    val = full_future_examples(val_examples)
    ev = make_evaluate(cfg, val, tc.eval_batch_size)
    evaluate = lambda st: ev(st.params, st.extra)
  rows = tc.batch_size if mesh is None else distributed.local_batch_size(tc.batch_size, mesh)
  batch_at = lambda step: data_lib.batch_at(train_examples, step, rows, tc.seed)
  return trainer.fit(state, step_fn, batch_at, evaluate, tc, folder, config_lib.to_dict(cfg),
                     desc="diffusion", max_minutes=max_minutes, progress=progress,
                     schedule=trainer.learning_rate_schedule(tc), compare=CONFIG_SECTIONS,
                     evaluate_state=True, mesh=mesh)


def load(workdir: str, use_prior: bool = True) -> tuple[Models, Config]:
  """(Models, Config) from the latest stage-2 checkpoint of a variant in WORKDIR."""
  ckpt = trainer.Checkpointer(os.path.join(workdir, stage_dir(use_prior)), read_only=True)
  try:
    cfg = config_lib.from_dict(ckpt.read_config())
    raw = ckpt.restore_raw()
  finally:
    ckpt.close()
  enc = raw["extra"]["encoder"]
  encoder_stage.check_params(enc, cfg, ckpt.directory)
  stats = latent.LatentStats(**{k: jnp.asarray(v) for k, v in raw["extra"]["stats"].items()})
  return Models(encoder=enc, denoiser=raw["params"], stats=stats), cfg
