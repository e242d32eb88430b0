"""Recovery examples: a displaced agent's target starts at its new pose and re-joins the log."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pcdiff_jax.config import PerturbConfig
from pcdiff_jax.model.features import AGENT_CHANNELS, AGENT_DIM, SceneFeatures
from pcdiff_jax.sim import geometry
from pcdiff_jax.training import perturb
from pcdiff_jax.training.data import Example, Targets

T, DT, V = 80, 0.1, 10.0


def _straight_batch(num_agents: int = 3) -> Example:
  """Agents driving straight at V along their own x; slot 0 is the SDC."""
  s = DT * jnp.arange(1, T + 1)
  fut = jnp.broadcast_to(jnp.stack([V * s, 0 * s], -1), (num_agents, T, 2))
  hist = jnp.zeros((num_agents, 11, AGENT_DIM)).at[:, -1, AGENT_CHANNELS.index("vel_x")].set(V)
  zeros = lambda *shape: jnp.zeros(shape)
  feats = SceneFeatures(**{f: None for f in SceneFeatures.__dataclass_fields__}).replace(
      agent_history=hist, agent_valid=jnp.ones(num_agents, bool),
      agent_types=jnp.ones(num_agents, jnp.int32),
      agent_center=jnp.stack([zeros(num_agents), 5.0 * jnp.arange(num_agents)], -1),
      agent_dir=jnp.tile(jnp.array([[0.0, 1.0]]), (num_agents, 1)))
  targets = Targets(future_xy=fut, future_yaw=zeros(num_agents, T), future_speed=jnp.full((num_agents, T), V),
                    future_valid=jnp.ones((num_agents, T), bool), current_speed=jnp.full(num_agents, V))
  return Example(feats=feats, targets=targets)


@pytest.mark.parametrize("delta,eps", [(1.0, 0.0), (-0.8, 0.1), (0.0, -0.12)])
def test_rejoin_starts_at_the_new_pose_and_meets_the_log(delta, eps):
  b = _straight_batch(1).targets
  xy, yaw = perturb.rejoin_targets(b.future_xy[0], b.future_yaw[0], b.future_speed[0], jnp.float32(V),
                                   jnp.float32(delta), jnp.float32(eps), 3.0, DT)
  # The first step continues from the displaced pose: ~V dt along the new heading.
  np.testing.assert_allclose(np.asarray(xy[0]), [V * DT, 0.0], atol=0.03)
  assert abs(float(yaw[0])) < 0.02
  # From 3 s on it is the log, seen from the displaced frame.
  log_new = geometry.to_local(b.future_xy[0], jnp.array([0.0, delta]), jnp.float32(eps))
  np.testing.assert_allclose(np.asarray(xy[30:]), np.asarray(log_new[30:]), atol=1e-4)
  np.testing.assert_allclose(np.asarray(yaw[30:]), -eps, atol=1e-5)
  # Smooth: no step is longer than the log's own by more than a few cm.
  steps = jnp.linalg.norm(jnp.diff(xy, axis=0), axis=-1)
  assert float(jnp.max(jnp.abs(steps - V * DT))) < 0.05


def test_perturb_moves_chosen_agents_only_and_never_the_sdc():
  batch = _straight_batch(3)
  out = perturb.perturb(batch, jax.random.key(0), PerturbConfig(prob=1.0, max_lateral=1.0, max_heading=0.1))
  moved = np.asarray(jnp.linalg.norm(out.feats.agent_center - batch.feats.agent_center, axis=-1))
  assert moved[0] == 0 and np.all(moved[1:] > 0) and np.all(moved[1:] <= 1.0 + 1e-6)
  # The lateral move is along the agent's left normal (its dir is +y, so left is -x).
  assert np.allclose(np.asarray(out.feats.agent_center[1:, 1]), [5.0, 10.0])
  np.testing.assert_allclose(np.linalg.norm(np.asarray(out.feats.agent_dir), axis=-1), 1.0, rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(out.feats.agent_history), np.asarray(batch.feats.agent_history))
  np.testing.assert_array_equal(np.asarray(out.targets.future_xy[0]), np.asarray(batch.targets.future_xy[0]))
  off = perturb.perturb(batch, jax.random.key(0), PerturbConfig(prob=0.0))
  assert off is batch


def test_perturb_is_jittable_with_batch_dims():
  batch = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), _straight_batch(3))
  fn = jax.jit(lambda b, k: perturb.perturb(b, k, PerturbConfig(prob=0.5)))
  out = fn(batch, jax.random.key(1))
  assert out.targets.future_xy.shape == (2, 3, T, 2)
  assert np.all(np.isfinite(np.asarray(out.targets.future_xy)))


def test_drop_history_hides_the_past_of_chosen_agents_and_keeps_the_current_step():
  batch = _straight_batch(64)
  hist = jnp.arange(64 * 11 * AGENT_DIM, dtype=jnp.float32).reshape(64, 11, AGENT_DIM) + 1.0
  batch = batch.replace(feats=batch.feats.replace(agent_history=hist,
                                                  agent_history_valid=jnp.ones((64, 11), bool),
                                                  agent_valid=jnp.arange(64) < 60))
  out = jax.jit(lambda b, k: perturb.drop_history(b, k, 0.5))(batch, jax.random.key(3))
  valid, h = np.asarray(out.feats.agent_history_valid), np.asarray(out.feats.agent_history)
  dropped = ~valid[:, :-1].any(-1)
  assert 15 < dropped[:60].sum() < 45 and not dropped[60:].any()   # padded slots are never chosen
  assert valid[:, -1].all()
  np.testing.assert_array_equal(h[:, -1], np.asarray(hist[:, -1]))              # the current step stays
  assert (h[dropped, :-1] == 0).all()
  np.testing.assert_array_equal(h[~dropped], np.asarray(hist)[~dropped])       # the others are untouched
  assert valid[~dropped].all()
  np.testing.assert_array_equal(np.asarray(out.targets.future_xy), np.asarray(batch.targets.future_xy))
  assert perturb.drop_history(batch, jax.random.key(3), 0.0) is batch
