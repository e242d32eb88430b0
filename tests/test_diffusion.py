"""The proposal-scaled VP diffusion: schedule, noising, DDIM vs DDPM, the guidance hook."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pcdiff_jax.model import diffusion as D

SCHED = D.linear_schedule(100, 1e-4, 5e-2)


def test_linear_schedule_values():
  betas = np.asarray(SCHED.betas, np.float64)
  np.testing.assert_allclose(betas[[0, -1]], [1e-4, 5e-2], rtol=1e-6)
  np.testing.assert_allclose(np.diff(betas), (5e-2 - 1e-4) / 99, rtol=1e-4)
  np.testing.assert_allclose(np.asarray(SCHED.alphas_cumprod), np.cumprod(1 - betas), rtol=1e-5)
  # The end of the chain keeps ~28% of the signal: why sampling starts from a shifted Gaussian.
  assert 0.07 < float(SCHED.alphas_cumprod[-1]) < 0.09


def test_q_sample_statistics():
  y0 = jnp.array([2.0, -1.0, 0.5])
  sigma = jnp.array([0.3, 1.0, 2.0])
  s = 60
  eps = jax.random.normal(jax.random.key(0), (200_000, 3))
  ys = np.asarray(D.q_sample(y0, jnp.asarray(s), eps, sigma, SCHED))
  a = float(SCHED.alphas_cumprod[s])
  np.testing.assert_allclose(ys.mean(0), np.sqrt(a) * np.asarray(y0), atol=0.01)
  np.testing.assert_allclose(ys.std(0), np.sqrt(1 - a) * np.asarray(sigma), rtol=0.01)
  # predict_y0 inverts q_sample given the true scaled noise.
  y0_back = D.predict_y0(jnp.asarray(ys[:5]), jnp.asarray(s), sigma * eps[:5], SCHED)
  np.testing.assert_allclose(np.asarray(y0_back), np.broadcast_to(y0, (5, 3)), atol=1e-4)


def _gaussian_denoiser(m, c, sigma):
  """The exact E[sigma eps | y_s] when y0 ~ N(m, c^2) (per dimension)."""
  def denoise(y, s):
    a = SCHED.alphas_cumprod[s]
    b2 = (1 - a) * sigma ** 2
    return jnp.sqrt(1 - a) * sigma ** 2 * (y - jnp.sqrt(a) * m) / (a * c ** 2 + b2)
  return denoise


@pytest.mark.parametrize("mu_offset", [0.0, 1.5])
def test_ddim_eta1_full_steps_matches_ddpm_and_data(mu_offset):
  """With the exact denoiser of a Gaussian toy, DDIM (100 steps, eta=1) and DDPM
  give the same distribution, whatever the start shift; started at the true
  mean, all samplers recover N(m, c^2). A sign or coefficient error in any
  update moves the moments. (A shifted start biases the samples toward the
  shift: that is the point of the proposal prior, so it is not tested away.)"""
  m, c = jnp.array([1.0, -2.0]), jnp.array([0.5, 0.4])
  sigma = jnp.array([0.8, 1.0])
  n = 40_000
  mu = jnp.broadcast_to(m + mu_offset, (n, 2))
  sig = jnp.broadcast_to(sigma, (n, 2))
  den = _gaussian_denoiser(m, c, sigma)
  run = lambda f: np.asarray(jax.jit(f)(jax.random.key(1)))
  ddim1 = run(lambda k: D.ddim_sample(den, mu, sig, SCHED, k, 100, eta=1.0))
  ddpm = run(lambda k: D.ddpm_sample(den, mu, sig, SCHED, k))
  ddim0 = run(lambda k: D.ddim_sample(den, mu, sig, SCHED, k, 100, eta=0.0))
  # DDIM with eta = 1 over all steps is the ancestral sampler: same distribution.
  np.testing.assert_allclose(ddim1.mean(0), ddpm.mean(0), atol=0.015)
  np.testing.assert_allclose(ddim1.std(0), ddpm.std(0), rtol=0.02)
  # All three recover the data up to the discretisation of 100 steps (the
  # ancestral samplers drop the posterior variance of y0: a few % narrower).
  for samples in (ddim1, ddpm, ddim0) if mu_offset == 0 else ():
    np.testing.assert_allclose(samples.mean(0), np.asarray(m), atol=0.02)
    np.testing.assert_allclose(samples.std(0), np.asarray(c), rtol=0.06)


def test_ddim_any_step_count_and_guidance_hook():
  den = lambda y, s: jnp.zeros_like(y)
  mu, sig = jnp.zeros((3, 4)), jnp.ones((3, 4))
  for n in (1, 2, 5, 10, 25, 100):
    steps = D.ddim_timesteps(100, n)
    assert len(steps) == n and steps[0] == 99 and (n == 1 or steps[-1] == 0) and np.all(np.diff(steps) < 0)
    out = D.ddim_sample(den, mu, sig, SCHED, jax.random.key(0), n)
    assert out.shape == (3, 4) and np.all(np.isfinite(np.asarray(out)))
  with pytest.raises(ValueError, match="DDIM steps"):
    D.ddim_timesteps(100, 0)
  # The hook replaces y0 at the last step only: the result is exactly its value.
  guide = lambda y0, y, s, i: jnp.full_like(y0, 7.0)
  out = D.ddim_sample(den, mu, sig, SCHED, jax.random.key(0), 5, guide=guide,
                      guide_steps=np.array([0, 0, 0, 0, 1], bool))
  np.testing.assert_allclose(np.asarray(out), 7.0, rtol=1e-5)
  unguided = D.ddim_sample(den, mu, sig, SCHED, jax.random.key(0), 5, guide=guide,
                           guide_steps=np.zeros(5, bool))
  assert not np.allclose(np.asarray(unguided), 7.0)


def test_prior_from_proposals():
  props = jnp.array([[[0.0, 1.0], [2.0, 1.0]]])          # (A=1, K=2, d=2)
  mu, sigma = D.prior_from_proposals(props, 0.3)
  np.testing.assert_allclose(np.asarray(mu), [[1.0, 1.0]])
  np.testing.assert_allclose(np.asarray(sigma), [[1.3, 0.3]])
  # Weighted by the encoder's probabilities: equal weights are the plain prior, a sure encoder
  # (p = 0.98 on one mode) gives a narrow prior about that mode.
  even = D.prior_from_proposals(props, 0.3, jnp.array([[0.5, 0.5]]))
  np.testing.assert_allclose(np.asarray(even[0]), [[1.0, 1.0]], atol=1e-6)
  np.testing.assert_allclose(np.asarray(even[1]), [[1.3, 0.3]], atol=1e-5)
  mu, sigma = D.prior_from_proposals(props, 0.3, jnp.array([[0.98, 0.02]]))
  np.testing.assert_allclose(np.asarray(mu), [[0.04, 1.0]], atol=1e-6)
  np.testing.assert_allclose(np.asarray(sigma), [[0.3 + 2 * np.sqrt(0.98 * 0.02), 0.3]], atol=1e-5)


def test_warm_start_keeps_a_consistent_plan_and_starts_where_asked():
  """A warm start noises `mu` (the previous plan) only to `start_step` and
  denoises from there: a plan the data agrees with stays put, whatever the
  noise draw, while a cold start lands anywhere in the data distribution."""
  m, c = jnp.array([1.0, -2.0]), jnp.array([0.5, 0.4])
  sigma = jnp.array([0.8, 1.0])
  n = 4000
  den = _gaussian_denoiser(m, c, sigma)
  plan = jnp.broadcast_to(m + jnp.array([0.3, -0.2]), (n, 2))       # a plausible plan, off the mean
  sig = jnp.broadcast_to(sigma, (n, 2))
  drift = lambda out: float(np.abs(np.asarray(out) - np.asarray(plan)).mean())
  warm = lambda s: drift(D.ddim_sample(den, plan, sig, SCHED, jax.random.key(0), 2, start_step=s))
  cold = drift(D.ddim_sample(den, jnp.broadcast_to(m, (n, 2)), sig, SCHED, jax.random.key(0), 5))
  # The less noise, the closer to the previous plan; all closer than a fresh sample.
  assert warm(2) < warm(10) < warm(20) < warm(40) < cold and warm(2) < 0.05
  # At step 0 the chain is the plan itself up to the first noise level (sqrt(1 - abar_0) = 1%).
  zero = D.ddim_sample(lambda y, s: jnp.zeros_like(y), plan, sig, SCHED, jax.random.key(1), 1, start_step=0)
  np.testing.assert_allclose(np.asarray(zero), np.asarray(plan), atol=0.06)
  np.testing.assert_array_equal(D.ddim_timesteps(100, 2, start_step=30), [30, 0])
  with pytest.raises(ValueError, match="start step"):
    D.ddim_timesteps(100, 2, start_step=100)
  with pytest.raises(ValueError, match="DDIM steps"):
    D.ddim_timesteps(100, 5, start_step=3)


@pytest.mark.parametrize("eta", [0.0, 1.0])
def test_either_chain_matches_the_chosen_sampler_under_vmap(eta):
  """`ddim_sample_either` is the cold sampler where asked and the warm one
  elsewhere, scene by scene in one vmapped call, noise included."""
  m, c = jnp.array([1.0, -2.0]), jnp.array([0.5, 0.4])
  sigma = jnp.array([0.8, 1.0])
  den = _gaussian_denoiser(m, c, sigma)
  mu = jnp.stack([jnp.broadcast_to(m, (3, 2)), jnp.broadcast_to(m + 0.3, (3, 2))])     # (2, 3, 2)
  sig = jnp.broadcast_to(sigma, mu.shape)
  keys = jax.random.split(jax.random.key(3), 2)
  cold = jnp.array([True, False])
  either = jax.vmap(lambda mu, sig, k, c: D.ddim_sample_either(den, mu, sig, SCHED, k, c, 5, 2, 30, eta))
  out = np.asarray(either(mu, sig, keys, cold))
  expect_cold = D.ddim_sample(den, mu[0], sig[0], SCHED, keys[0], 5, eta)
  expect_warm = D.ddim_sample(den, mu[1], sig[1], SCHED, keys[1], 2, eta, start_step=30)
  np.testing.assert_allclose(out[0], np.asarray(expect_cold), rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(out[1], np.asarray(expect_warm), rtol=1e-5, atol=1e-5)


def test_given_noise_starts_the_cold_chain_only():
  """Consistent noise: the given draw starts a cold chain; a warm start draws its
  own (the same draw at every warm replan pushed every agent the same way)."""
  m, c = jnp.array([1.0, -2.0]), jnp.array([0.5, 0.4])
  sigma = jnp.array([0.8, 1.0])
  den = _gaussian_denoiser(m, c, sigma)
  mu = jnp.broadcast_to(m, (3, 2))
  sig = jnp.broadcast_to(sigma, mu.shape)
  key, noise = jax.random.key(5), 3.0 * jnp.ones((3, 2))
  run = lambda cold, init: D.ddim_sample_either(den, mu, sig, SCHED, key, jnp.bool_(cold), 5, 2, 30, 0.0,
                                                init_noise=init)
  np.testing.assert_allclose(np.asarray(run(True, noise)),
                             np.asarray(D.ddim_sample(den, mu, sig, SCHED, key, 5, 0.0, init_noise=noise)),
                             rtol=1e-5, atol=1e-5)
  np.testing.assert_allclose(np.asarray(run(False, noise)), np.asarray(run(False, None)), rtol=1e-6)
