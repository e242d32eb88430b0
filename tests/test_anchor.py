"""Anchor inputs (`DenoiserConfig.anchor_inputs`): the denoiser conditioned on one proposal per agent."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax.config import get_config
from pcdiff_jax.model import denoiser, features, planner

CFG = get_config("tiny")
ANCHORED = dataclasses.replace(CFG, diffusion=dataclasses.replace(
    CFG.diffusion, denoiser=dataclasses.replace(CFG.diffusion.denoiser, anchor_inputs=True)))


@pytest.fixture(scope="module")
def cond(tiny_models):
  """The tiny models' conditioning of make_scene at t = 10 (batch 1)."""
  state = make_scene(num_steps=31).replace(timestep=jnp.int32(10))
  feats = jax.tree_util.tree_map(lambda a: a[None], features.scene_features(state, CFG.features))
  return jax.jit(lambda f: planner.condition(tiny_models.encoder, tiny_models.stats, f, CFG))(feats)


def test_a_model_trained_without_anchors_loads_with_them_and_then_reads_them(tiny_models, cond):
  """The zero-initialised projection leaves the output unchanged whatever the
  anchor; once trained (here: random weights) two anchors give two outputs,
  and a missing anchor is an error, not a silent zero."""
  params = denoiser.with_new_inputs(tiny_models.denoiser, ANCHORED.diffusion.denoiser)
  assert "in_anchor" in params["params"] and "in_anchor" not in tiny_models.denoiser["params"]
  y = cond.mu + 0.5
  dc, ac = CFG.diffusion.denoiser, ANCHORED.diffusion.denoiser
  run = jax.jit(lambda p, a: denoiser.apply(p, y, jnp.int32(40), cond.inputs, ac, anchor=a))
  before = jax.jit(lambda p: denoiser.apply(p, y, jnp.int32(40), cond.inputs, dc))(tiny_models.denoiser)
  first, last = cond.proposals[..., 0, :], cond.proposals[..., -1, :]
  np.testing.assert_allclose(run(params, first), before, atol=1e-5)
  np.testing.assert_allclose(run(params, last), before, atol=1e-5)
  def randomised(layer, seed):   # untrained, the output projection is zero too
    kernel = params["params"][layer]["kernel"]
    return {"kernel": jax.random.normal(jax.random.key(seed), kernel.shape), "bias": jnp.zeros(kernel.shape[1:])}
  trained = {**params, "params": {**params["params"], "in_anchor": randomised("in_anchor", 0),
                                  "out": randomised("out", 1)}}
  valid = np.asarray(cond.inputs.agent_valid)
  assert np.abs(np.asarray(run(trained, first) - run(trained, last))[valid]).max() > 1e-3
  with pytest.raises(ValueError, match="anchor"):
    denoiser.apply(params, y, jnp.int32(40), cond.inputs, ac)
  # The sampler draws anchors itself when it is given none.
  plans = jax.jit(lambda p, k: planner.sample(p, cond, ANCHORED, k, 2))(trained, jax.random.key(1))
  assert plans.shape == y.shape and bool(jnp.all(jnp.isfinite(plans)))


def test_anchors_are_drawn_from_the_probabilities_or_kept_near_the_previous_plan(cond):
  """Without a previous plan each agent's anchor is a proposal drawn by its
  probability (one-hot here: that proposal); with one, the proposal nearest
  it (tau 0), or the probabilities again for a wide tau. The prior centre moves to the anchor; a model without anchors is left as is."""
  num_agents, k = cond.probs.shape[-2:]
  choice = jnp.arange(num_agents) % k
  cond = cond.replace(probs=jax.nn.one_hot(choice, k)[None])
  assert planner.draw_anchor(cond, CFG, jax.random.key(0)) is cond
  drawn = planner.draw_anchor(cond, ANCHORED, jax.random.key(0))
  expected = jnp.take_along_axis(cond.proposals, choice[None, :, None, None], -2)[..., 0, :]
  np.testing.assert_allclose(drawn.anchor, expected)
  np.testing.assert_allclose(drawn.mu, expected)
  previous = cond.proposals[..., 1, :] + 0.01                                # near proposal 1
  has = jnp.arange(num_agents) < 3
  kept = planner.draw_anchor(cond, ANCHORED, jax.random.key(0), previous, has)
  np.testing.assert_allclose(kept.anchor[0, :3], cond.proposals[0, :3, 1])
  np.testing.assert_allclose(kept.anchor[0, 3:], expected[0, 3:])
  loose = planner.draw_anchor(cond, ANCHORED, jax.random.key(0), previous, has, tau=1e6)
  np.testing.assert_allclose(loose.anchor, expected)                         # the probabilities decide

