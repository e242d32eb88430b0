"""Stage 1: train the scene encoder (SIMPL proposals) and load it back.

`train(config, train_examples, val_examples, workdir)` runs `trainer.fit` with
the WTA + classification loss of `encoder_loss`; `load(workdir)` returns the
trained parameters and the Config they were trained with (from the
checkpoint), for the later stages and the policy.
"""
from __future__ import annotations

import os
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from pcdiff_jax import config as config_lib
from pcdiff_jax import distributed
from pcdiff_jax.config import Config
from pcdiff_jax.model import encoder
from pcdiff_jax.training import data as data_lib
from pcdiff_jax.training import encoder_loss, perturb, trainer
from pcdiff_jax.training.data import Example

STAGE_DIR = "encoder"
# The SIMPL-AR baseline's own encoder, when a model folder has one: stage 1
# fine-tuned on SIMPL-AR's closed-loop states (`experiments.finetune --policy
# simpl-ar`). The diffusion policy always reads STAGE_DIR.
SIMPL_AR_DIR = "simpl_ar"
# Config sections that define this stage: a resumed run must match them.
CONFIG_SECTIONS = ("features", "encoder", "encoder_train")


def cache_spec(cfg: Config) -> data_lib.CacheSpec:
  return data_lib.CacheSpec(features=cfg.features, horizon=cfg.encoder.horizon,
                            current_steps=tuple(cfg.encoder_train.current_steps))


def make_loss_fn(cfg: Config):
  """Training loss; batches get the recovery examples of `encoder_train.perturb`
  and the hidden histories of `encoder_train.history_dropout`."""
  def loss_fn(params, batch: Example, rng):
    rng, k_perturb = jax.random.split(rng)
    batch = perturb.perturb(batch, k_perturb, cfg.encoder_train.perturb, cfg.kinematics.dt)
    # Its own key folded off, so runs without dropout draw as before it existed.
    batch = perturb.drop_history(batch, jax.random.fold_in(k_perturb, 1), cfg.encoder_train.history_dropout)
    out = encoder.apply(params, batch.feats, cfg.encoder, rng=rng)
    return encoder_loss.proposal_loss(out, batch.targets, cls_weight=cfg.encoder_train.cls_weight)
  return loss_fn


def make_evaluate(cfg: Config, examples: Example, batch_size: int):
  """params -> validation metrics (minADE6, minFDE6, miss rate, brier-minFDE, CV) over `examples`."""
  @jax.jit
  def sums(params, batch: Example, mask):
    targets = batch.targets.replace(future_valid=batch.targets.future_valid & mask[:, None, None])
    out = encoder.apply(params, batch.feats, cfg.encoder)
    return encoder_loss.prediction_metrics(out, batch.feats, targets)

  def evaluate(params) -> dict:
    total = None
    for batch, mask in data_lib.eval_batches(examples, batch_size):
      s = jax.device_get(sums(params, batch, mask))
      total = s if total is None else jax.tree_util.tree_map(np.add, total, s)
    return encoder_loss.finalize(total)
  return evaluate


def init_params(cfg: Config, examples: Example, seed: int) -> Any:
  first = jax.tree_util.tree_map(lambda a: a[:1], examples.feats)
  return encoder.init(jax.random.key(seed), first, cfg.encoder)


def train(cfg: Config, train_examples: Example, val_examples: Optional[Example], workdir: str,
          max_minutes: Optional[float] = None, progress: bool = True, mesh: Optional[Mesh] = None):
  """Trains (or resumes) stage 1 in WORKDIR/encoder. Returns (state, val metrics).

  mesh: data-parallel over its devices (`pcdiff_jax.distributed`); then
  `train_examples` are this host's and it feeds its share of each global batch.
  """
  tc = cfg.encoder_train
  stage_dir = os.path.join(workdir, STAGE_DIR)
  tx = trainer.make_optimizer(tc)
  params = init_params(cfg, train_examples, tc.seed)
  state = trainer.create_state(params, tx, tc.seed)
  step_fn = trainer.make_train_step(make_loss_fn(cfg), tx, mesh=mesh)
  evaluate = (make_evaluate(cfg, val_examples, tc.eval_batch_size)
              if val_examples is not None else None)
  rows = tc.batch_size if mesh is None else distributed.local_batch_size(tc.batch_size, mesh)
  batch_at = lambda step: data_lib.batch_at(train_examples, step, rows, tc.seed)
  return trainer.fit(state, step_fn, batch_at, evaluate, tc, stage_dir, config_lib.to_dict(cfg),
                     desc="encoder", max_minutes=max_minutes, progress=progress,
                     schedule=trainer.learning_rate_schedule(tc), compare=CONFIG_SECTIONS, mesh=mesh)


def load(workdir: str, stage_dir: str = STAGE_DIR) -> tuple[Any, Config]:
  """(params, Config) of the latest stage-1 checkpoint in WORKDIR/<stage_dir>."""
  ckpt = trainer.Checkpointer(os.path.join(workdir, stage_dir), read_only=True)
  try:
    cfg = config_lib.from_dict(ckpt.read_config())
    params = ckpt.restore_raw()["params"]
  finally:
    ckpt.close()
  check_params(params, cfg, ckpt.directory)
  return params, cfg


def simpl_ar_dir(workdir: str) -> str:
  """The stage folder SIMPL-AR reads in WORKDIR: its own (SIMPL_AR_DIR) when
  there is one, else the shared encoder's."""
  return SIMPL_AR_DIR if os.path.isdir(os.path.join(workdir, SIMPL_AR_DIR)) else STAGE_DIR


def load_simpl_ar(workdir: str) -> tuple[Any, Config]:
  """(params, Config) of the encoder the SIMPL-AR baseline runs with in WORKDIR."""
  return load(workdir, simpl_ar_dir(workdir))


def check_params(params: Any, cfg: Config, where: str) -> None:
  """Raises CheckpointMismatch unless `params` fit the encoder of `cfg`."""
  like = jax.eval_shape(lambda: encoder.init(jax.random.key(0), zero_features(cfg), cfg.encoder))
  got = jax.tree_util.tree_map(lambda a: tuple(a.shape), params)
  want = jax.tree_util.tree_map(lambda a: tuple(a.shape), like)
  if got != want:
    raise trainer.CheckpointMismatch(f"{where}: encoder parameters do not match its saved config")


def zero_features(cfg: Config):
  """A SceneFeatures of zeros with the padded sizes of `cfg.features` (one scene)."""
  from pcdiff_jax.model.features import AGENT_DIM, SceneFeatures
  f = cfg.features
  a, h, m, p = f.max_agents, f.history_steps, f.max_polylines, f.points_per_polyline
  z = lambda *s, dtype=jnp.float32: jnp.zeros(s, dtype)
  return SceneFeatures(
      agent_history=z(a, h, AGENT_DIM), agent_history_valid=z(a, h, dtype=bool),
      agent_valid=z(a, dtype=bool), agent_index=z(a, dtype=jnp.int32),
      agent_types=z(a, dtype=jnp.int32), agent_center=z(a, 2), agent_dir=z(a, 2),
      map_points=z(m, p, 2), map_valid=z(m, dtype=bool), map_types=z(m, dtype=jnp.int32),
      map_kind=z(m, dtype=jnp.int32), map_traffic_light=z(m, dtype=jnp.int32),
      map_ids=z(m, dtype=jnp.int32), map_center=z(m, 2), map_dir=z(m, 2),
      scene_xy=z(2), scene_yaw=z(), timestep=z(dtype=jnp.int32))

