"""The shipped model (checkpoints/): it loads with one call and drives the real WOMD record."""
from __future__ import annotations

import os

import jax
import numpy as np
import pytest

import pcdiff_jax
from pcdiff_jax import metrics, policy, shipped
from pcdiff_jax.sim import env

NUM_STEPS = 5


@pytest.fixture(scope="module")
def model():
  folder = shipped.checkpoint_dir()
  if not os.path.isdir(folder):
    pytest.fail(f"the shipped model is missing from {folder}: it is committed with the code")
  return pcdiff_jax.pretrained()


def test_shipped_model_has_a_card_and_drives_the_real_record(model, real_state):
  models, cfg = model
  assert os.path.exists(os.path.join(shipped.checkpoint_dir(), "MODEL_CARD.md"))
  assert models.stats.dim == cfg.diffusion.latent_dim
  actor = policy.actor(cfg, policy.PolicyConfig(ddim_steps=2, warm_start=True))
  start = env.reset(real_state)
  run = jax.jit(lambda s, r, m: env.rollout(s, actor, NUM_STEPS, r, params=m).final_state)
  final = run(start, jax.random.key(0), models)
  controlled, lost = metrics.lost_agents(final, env.WOMD_INIT_STEPS - 1, NUM_STEPS)
  assert int(controlled.sum()) == cfg.features.max_agents - 1       # 73 objects valid at t = 10
  assert int(lost.sum()) == 0
  steps = slice(env.WOMD_INIT_STEPS, env.WOMD_INIT_STEPS + NUM_STEPS)
  xy = np.asarray(final.sim_trajectory.xy)[np.asarray(controlled)][:, steps]
  assert np.all(np.isfinite(xy))
  # A trained model keeps moving agents near their log over half a second (an untrained one
  # sends them metres off): mean displacement from the log under 1 m.
  log = np.asarray(final.log_trajectory.xy)[np.asarray(controlled)][:, steps]
  both = np.asarray(final.log_trajectory.valid)[np.asarray(controlled)][:, steps]
  assert float(np.linalg.norm(xy - log, axis=-1)[both].mean()) < 1.0
  enc, enc_cfg = pcdiff_jax.pretrained(stage="encoder")
  assert enc_cfg.encoder == cfg.encoder
