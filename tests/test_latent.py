"""The PCA action latent: inverse dynamics, fit, encode/decode round trip, rollout."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from pcdiff_jax.model import latent as L

T = 80


def _smooth_actions(n, seed=0):
  """Random smooth action sequences (n, T, 2): sums of a few sinusoids."""
  rng = np.random.default_rng(seed)
  t = np.linspace(0, 1, T)
  freqs = np.arange(1, 5)
  coef = rng.normal(size=(n, 2, len(freqs)))
  return np.einsum("nck,tk->ntc", coef, np.sin(np.pi * t[:, None] * freqs)).astype(np.float32) * [1.0, 0.1]


def test_fit_round_trip_and_projection():
  u = _smooth_actions(500)
  full = L.fit(u, 2 * T)
  np.testing.assert_allclose(np.asarray(L.decode(L.encode(jnp.asarray(u), full), full)), u, atol=1e-3)
  small = L.fit(u, 8)                                     # 8 = rank of the data
  assert float(jnp.sum(small.explained)) > 0.999
  np.testing.assert_allclose(np.asarray(L.decode(L.encode(jnp.asarray(u), small), small)), u, atol=1e-3)
  y = jnp.asarray(np.random.default_rng(1).normal(size=(7, 8)), jnp.float32)
  np.testing.assert_allclose(np.asarray(L.encode(L.decode(y, small), small)), np.asarray(y), atol=1e-4)
  with pytest.raises(ValueError, match="latent dim"):
    L.fit(u, 2 * T + 1)


def test_inverse_then_rollout_reconstructs_the_path():
  """A curving, accelerating path in the agent frame -> actions -> latent -> f."""
  t = np.arange(1, T + 1) * 0.1
  v0, acc, yaw_rate = 8.0, 0.5, 0.15
  speed = v0 + acc * t
  yaw = yaw_rate * t
  dx, dy = speed * np.cos(yaw) * 0.1, speed * np.sin(yaw) * 0.1
  xy = np.stack([np.cumsum(dx), np.cumsum(dy)], -1).astype(np.float32)
  valid = np.ones(T, bool)
  actions, ok = L.actions_from_future(jnp.asarray(xy), jnp.asarray(yaw, jnp.float32),
                                      jnp.asarray(speed, jnp.float32), jnp.asarray(valid),
                                      jnp.float32(v0))
  assert bool(jnp.all(ok))
  np.testing.assert_allclose(np.asarray(actions[5:, 0]), acc, atol=0.05)
  np.testing.assert_allclose(np.asarray(actions[5:, 1]), yaw_rate, atol=0.01)
  stats = L.fit(np.concatenate([np.asarray(actions)[None], _smooth_actions(300)]), 16)
  states = L.rollout(L.encode(actions, stats), jnp.float32(v0), stats)
  err = np.linalg.norm(np.asarray(states[:, :2]) - xy, axis=-1)
  assert err.max() < 0.5, err.max()
  # Proposals (positions only) give the same actions.
  from_pos = L.actions_from_positions(jnp.asarray(xy), jnp.float32(v0))
  np.testing.assert_allclose(np.asarray(from_pos), np.asarray(actions), atol=1e-3)


def test_path_inverse_does_not_oscillate_after_a_clipped_start():
  """A proposal at 10 m/s for an agent now at 5 m/s: one clipped first action,
  then zeros (the closed-loop tracker would alternate to catch up)."""
  s = np.arange(1, T + 1, dtype=np.float32)
  xy = np.stack([1.0 * s, 0 * s], -1)                             # 10 m/s straight
  actions = np.asarray(L.actions_from_positions(jnp.asarray(xy), jnp.float32(5.0)))
  assert actions[0, 0] == pytest.approx(10.0)                      # (10 - 5) / 0.1, clipped
  np.testing.assert_allclose(actions[1:], 0.0, atol=1e-3)


def test_a_path_fit_follows_a_jittery_path_with_an_in_distribution_latent():
  """Positions with 0.1 m of jitter around an in-distribution rollout: the
  inverse of the jittery positions projects to a latent whose rollout misses
  the path by metres; the MAP fit follows it, with a latent nearer the true
  one and a smaller whitened norm."""
  import jax
  stats = L.fit(_smooth_actions(500), 8)
  scale = jnp.sqrt(L.prior_variance(stats))
  y_true = jnp.asarray(np.random.default_rng(3).normal(size=(4, 8)), jnp.float32) * scale
  v0 = jnp.full((4,), 8.0)
  clean = L.rollout(y_true, v0, stats)[..., :2]
  xy = clean + 0.1 * jax.random.normal(jax.random.key(0), clean.shape)
  projected = L.encode(L.actions_from_positions(xy, v0), stats)
  fitted = L.fit_to_path(projected, xy, jnp.ones(xy.shape[:-1], bool), v0, stats, sigma=0.3)
  err = lambda y: float(jnp.mean(jnp.linalg.norm(L.rollout(y, v0, stats)[..., :2] - clean, axis=-1)))
  whitened = lambda y: float(jnp.mean(L.whitened_rms(y, stats)))
  assert err(fitted) < 0.2 * err(projected), (err(fitted), err(projected))
  assert whitened(fitted - y_true) < whitened(projected - y_true)
  assert whitened(fitted) < whitened(projected)
