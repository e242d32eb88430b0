"""Refit the encoder's proposal head on logged examples, with its trunk frozen.

The SFT trunk's agent and map tokens are the denoiser's context; the proposal
head (`head`, and `head_lane` when the encoder has lane inputs) turns each
agent token into K proposals. Refitting only the head on a mix of sources
(real WOMD scenes next to synthetic ones) moves the proposals, and the prior
built from them, towards real drivers while the tokens stay. The trunk runs
once per example (`trunk_outputs`), so thousands of steps take minutes on a
CPU. The denoiser reads the proposals too: re-train it on the new ones
(`experiments.finetune --encoder-from`).
"""
from __future__ import annotations

import functools
import types
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from pcdiff_jax.config import Config, TrainConfig
from pcdiff_jax.model import encoder, lane_context
from pcdiff_jax.sim.datatypes import Array
from pcdiff_jax.training import encoder_loss, trainer
from pcdiff_jax.training.data import Example, Targets

HEAD_PARAMS = ("head", "head_lane")
MOVING = 2.0   # m/s: the speed-bias metrics cover agents moving faster at t


@struct.dataclass
class TrunkOutputs:
  """What the head reads, per example: tokens (N, A, d), lane (N, A, L) (L = 0
  without lane inputs), speed (N, A) forward speed at t, valid (N, A), last
  (N, A, C) the history's last step (for the constant-velocity reference),
  and the examples' targets."""
  tokens: Array
  lane: Array
  speed: Array
  valid: Array
  last: Array
  targets: Targets


def head_params(params: Any) -> dict:
  """The trainable part of encoder params: {name: subtree} for HEAD_PARAMS present."""
  inner = params["params"]
  return {k: inner[k] for k in HEAD_PARAMS if k in inner}


def with_head(params: Any, head: dict) -> Any:
  """Encoder params with the head subtrees replaced."""
  return {**params, "params": {**params["params"], **head}}


def trunk_outputs(params: Any, cfg: Config, examples: Example, batch_size: int = 16) -> TrunkOutputs:
  """Runs the frozen trunk over every example (numpy in, numpy out)."""
  ec = cfg.encoder

  @jax.jit
  def run(feats):
    out = encoder.apply(params, feats, ec)
    hist = jnp.where(feats.agent_history_valid[..., None] & feats.agent_valid[..., None, None],
                     feats.agent_history, 0.0)
    lane = (lane_context.lane_inputs(feats) if ec.lane_inputs
            else jnp.zeros(feats.agent_valid.shape + (0,), jnp.float32))
    return out.agent_tokens, lane, hist[..., -1, encoder.VX], out.agent_valid, hist[..., -1, :]

  n = int(examples.feats.agent_valid.shape[0])
  parts = []
  for start in range(0, n, batch_size):
    idx = np.minimum(np.arange(start, start + batch_size), n - 1)   # a fixed shape: one compile
    feats = jax.tree_util.tree_map(lambda a: a[idx], examples.feats)
    keep = min(batch_size, n - start)
    parts.append([np.asarray(x)[:keep] for x in jax.device_get(run(feats))])
  cols = [np.concatenate([p[i] for p in parts]) for i in range(5)]
  return TrunkOutputs(*cols, targets=examples.targets)


def apply_head(head: dict, cfg: Config, trunk: TrunkOutputs):
  """(trajectories (..., A, K, T, 2), logits (..., A, K)) as `encoder.apply`
  computes them from these tokens (tests/test_head_refit.py checks it)."""
  ec = cfg.encoder
  h = trunk.tokens
  if "head_lane" in head:
    h = h + trunk.lane @ head["head_lane"]["kernel"] + head["head_lane"]["bias"]
  module = encoder.ProposalHead(ec.d_model, ec.num_modes, ec.bezier_degree, ec.proposal_scale,
                                ec.anchor_velocity, ec.horizon * encoder.DT)
  flat = lambda x, k: x.reshape((-1,) + x.shape[-k:])
  logits, ctrl = jax.vmap(lambda a, s: module.apply({"params": head["head"]}, a, s))(
      flat(h, 2), flat(trunk.speed, 1))
  batch = h.shape[:-2]
  logits, ctrl = logits.reshape(batch + logits.shape[1:]), ctrl.reshape(batch + ctrl.shape[1:])
  ctrl = jnp.where(trunk.valid[..., None, None, None], ctrl, 0.0)
  basis, _ = encoder.bezier_basis(ec.bezier_degree, ec.horizon)
  traj = jnp.einsum("ts,...aksc->...aktc", basis, ctrl, precision=jax.lax.Precision.HIGHEST)
  return traj, logits


def _output(head, cfg, trunk):
  traj, logits = apply_head(head, cfg, trunk)
  return types.SimpleNamespace(trajectories=traj, logits=logits, probs=jax.nn.softmax(logits, -1),
                               agent_valid=trunk.valid)


def loss(head: dict, cfg: Config, trunk: TrunkOutputs) -> tuple[Array, dict]:
  """Stage 1's WTA + classification loss of the refit head."""
  return encoder_loss.proposal_loss(_output(head, cfg, trunk), trunk.targets,
                                    cls_weight=cfg.encoder_train.cls_weight)


def take(trunk: TrunkOutputs, idx) -> TrunkOutputs:
  return jax.tree_util.tree_map(lambda a: a[idx], trunk)


def mixed_batch_at(sources: Sequence[TrunkOutputs], shares: Sequence[float], step: int,
                   batch_size: int, seed: int) -> TrunkOutputs:
  """The batch of global `step`: round(share * batch_size) rows of each source
  (the last takes the rest), drawn with replacement; a pure function of (seed, step)."""
  counts = [int(round(s * batch_size)) for s in shares[:-1]]
  counts.append(batch_size - sum(counts))
  rng = np.random.default_rng([seed, step])
  parts = [take(src, rng.integers(0, src.valid.shape[0], n)) for src, n in zip(sources, counts) if n > 0]
  return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *parts)


def refit(params: Any, cfg: Config, sources: Sequence[TrunkOutputs], shares: Sequence[float],
          train_cfg: TrainConfig, workdir: str, config: dict, progress: bool = True) -> Any:
  """Trains the head (resumable in WORKDIR) on mixed batches; returns the encoder params with it."""
  tx = trainer.make_optimizer(train_cfg)
  # A copy: the train step donates its state, and `params` stays the caller's.
  head = jax.tree_util.tree_map(lambda a: jnp.array(a, copy=True), head_params(params))
  state = trainer.create_state(head, tx, train_cfg.seed)
  step_fn = trainer.make_train_step(lambda head, batch, rng: loss(head, cfg, batch), tx)
  batch_at = lambda step: mixed_batch_at(sources, shares, step, train_cfg.batch_size, train_cfg.seed)
  state, _ = trainer.fit(state, step_fn, batch_at, None, train_cfg, workdir, config, desc="head",
                         progress=progress, schedule=trainer.learning_rate_schedule(train_cfg))
  return with_head(params, jax.device_get(state.params))


@functools.partial(jax.jit, static_argnums=1)
def _metric_sums(head: dict, cfg: Config, batch: TrunkOutputs) -> dict:
  """`evaluate`'s sums over one batch (compiled once per config and batch size)."""
  out = _output(head, cfg, batch)
  s = encoder_loss.prediction_metrics(out, types.SimpleNamespace(agent_history=batch.last[..., None, :]),
                                      batch.targets)
  dt = encoder.DT
  speed = jnp.linalg.norm(jnp.diff(out.trajectories, axis=-2), axis=-1) / dt      # (..., A, K, T-1)
  top = jnp.take_along_axis(speed, jnp.argmax(out.probs, -1)[..., None, None], -2)[..., 0, :]
  logged = jnp.linalg.norm(jnp.diff(batch.targets.future_xy, axis=-2), axis=-1) / dt
  pairs = batch.targets.future_valid[..., 1:] & batch.targets.future_valid[..., :-1]
  moving = batch.valid & (batch.speed > MOVING)
  for name, j in (("speed_bias_1s", 9), ("speed_bias_3s", 29)):
    ok = moving & pairs[..., j]
    s[name] = jnp.sum(jnp.where(ok, top[..., j] - logged[..., j], 0.0))
    s[name + "_count"] = jnp.sum(ok).astype(jnp.float32)
  return s


def evaluate(head: dict, cfg: Config, trunk: TrunkOutputs, batch_size: int = 32) -> dict:
  """Stage 1's prediction metrics (minADE6, minFDE6, miss rate, brier-minFDE)
  and the most likely proposal's speed minus the log's at 1 s and 3 s for
  agents moving at t (`speed_bias_1s`, `speed_bias_3s`, m/s): a negative
  bias is a predictor that brakes where the drivers did not."""
  n = trunk.valid.shape[0]
  total = None
  for start in range(0, n, batch_size):
    idx = np.arange(start, start + batch_size)
    batch = take(trunk, np.minimum(idx, n - 1))
    batch = batch.replace(valid=batch.valid & (idx < n)[:, None])   # padding rows score nothing
    s = jax.device_get(_metric_sums(head, cfg, batch))
    total = s if total is None else {k: total[k] + s[k] for k in s}
  biases = {k: float(total[k]) / max(float(total[k + "_count"]), 1.0)
            for k in ("speed_bias_1s", "speed_bias_3s")}
  core = {k: v for k, v in total.items() if not k.startswith("speed_bias")}
  return {**encoder_loss.finalize(core), **biases}
