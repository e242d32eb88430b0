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


def test_shipped_simpl_ar_baseline_has_a_lane_aware_encoder(model, real_state):
  """The SIMPL-AR baseline's encoder (`finetune --policy simpl-ar --lane-inputs`,
  kept in the folder's simpl_ar/ because ours conditions on a head refit for
  it): it loads with one call, has the lane-relative inputs and ours'
  architecture, and its most likely proposal on the real record is within a
  few metres of where each logged agent is 1 s later."""
  from pcdiff_jax.model import encoder, features
  from pcdiff_jax.training import encoder_stage
  models, cfg = model
  params, sa_cfg = pcdiff_jax.pretrained(stage="simpl-ar")
  assert sa_cfg.encoder.lane_inputs and cfg.encoder == sa_cfg.encoder
  assert "in_lane" in params["params"]
  assert encoder_stage.simpl_ar_dir(shipped.checkpoint_dir()) == encoder_stage.SIMPL_AR_DIR
  start = env.reset(real_state)
  feats = jax.jit(lambda st: features.scene_features(st, sa_cfg.features))(start)
  out = jax.jit(encoder.apply, static_argnums=2)(params, feats, sa_cfg.encoder)
  xy, _ = encoder.proposals_to_world(out, feats)                              # (A, K, T, 2)
  top = np.asarray(out.probs).argmax(-1)
  at_1s = np.asarray(xy)[np.arange(top.shape[0]), top, 9]                     # step t + 10
  obj = np.asarray(feats.agent_index)
  t = env.WOMD_INIT_STEPS - 1 + 10
  log = np.asarray(real_state.log_trajectory.xy)[obj, t]
  ok = np.asarray(feats.agent_valid) & np.asarray(real_state.log_trajectory.valid)[obj, t]
  assert ok.sum() > 20
  assert float(np.median(np.linalg.norm(at_1s - log, axis=-1)[ok])) < 2.0


def test_every_model_folder_with_weights_has_a_card_and_loads_by_name(model):
  """checkpoints/*: the default model, and any other folder with weights,
  loads by name and has its card. Older versions live in git tags
  (CHANGELOG.md)."""
  root = os.path.dirname(shipped.checkpoint_dir())
  names = sorted(n for n in os.listdir(root) if os.path.isdir(os.path.join(root, n, "diffusion")))
  assert shipped.DEFAULT_NAME in names
  for name in names:
    assert os.path.exists(os.path.join(root, name, "MODEL_CARD.md")), name
    models, cfg = pcdiff_jax.pretrained(name)
    assert models.stats.dim == cfg.diffusion.latent_dim, name


def test_diagnose_starters_lists_the_slow_agents_the_log_drives_away(womd_path, tmp_path):
  """`experiments.diagnose starters` on the real record: every row is an evaluated agent slower
  than 3 m/s at the start that the log carries more than 5 m, with the model's six proposals
  (probabilities summing to 1) and their probability-weighted travel."""
  import json
  from experiments import diagnose
  from pcdiff_jax.data import realism
  out = tmp_path / "starters.json"
  diagnose.main(["--checkpoint", shipped.checkpoint_dir(), "--scenarios", womd_path, "--num-scenes", "1",
                 "--out", str(out), "starters"])
  rows = json.loads(out.read_text())["rows"]
  assert rows, "the real record has a slow starter (a car that pulls away from standstill)"
  for row in rows:
    assert abs(row["speed"]) < realism.STARTER_SPEED and row["log_travel"] > realism.STARTER_TRAVEL
    travel, probs = np.array(row["proposals"]).T
    assert len(probs) == 6 and probs.sum() == pytest.approx(1.0, abs=1e-4) and np.all(np.diff(probs) <= 0)
    assert row["expected_travel"] == pytest.approx(float(np.sum(travel * probs)), rel=1e-5)
