"""The joint denoiser's parameters: built in one jitted call at any dropout rate."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import pytest

from conftest import make_scene
from pcdiff_jax.config import get_config
from pcdiff_jax.model import denoiser, features, planner

CFG = get_config("tiny")


@pytest.mark.parametrize("dropout", [0.0, 0.1])
def test_init_inside_a_jitted_build_at_any_dropout(tiny_models, dropout):
  """`experiments.bench` builds untrained models in one jitted call: the
  denoiser's `deterministic` flag must stay static there (a traced one broke
  dropout's rate check for the shipped config's 0.1)."""
  cfg = dataclasses.replace(CFG.diffusion.denoiser, dropout=dropout)
  state = make_scene(num_steps=31).replace(timestep=jnp.int32(10))

  @jax.jit
  def build(s):
    feats = jax.tree_util.tree_map(lambda a: a[None], features.scene_features(s, CFG.features))
    cond = planner.condition(tiny_models.encoder, tiny_models.stats, feats, CFG)
    one = jax.tree_util.tree_map(lambda a: a[0], cond.inputs)
    return denoiser.init(jax.random.key(1), cond.mu[0], jnp.int32(0), one, cfg)

  params = build(state)
  like = jax.tree_util.tree_map(jnp.shape, tiny_models.denoiser)
  assert jax.tree_util.tree_map(jnp.shape, params) == like
