"""A controlled agent is never lost: newcomers near the SDC and a passing car do
not push any controlled agent out of the modelled set, for every method."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax import baselines, evaluation, metrics, policy
from pcdiff_jax.baselines import idm, simpl_ar
from pcdiff_jax.config import MetricsConfig, get_config
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model.guidance import GuidanceConfig
from pcdiff_jax.sim import env

CFG = get_config("tiny")          # 9 modelled agents: the SDC + 8 controlled
NUM_STEPS = 48
START = env.WOMD_INIT_STEPS - 1
APPEAR = 13                       # the newcomers' first valid step
NEWCOMERS = (10, 11)
PASSER = 9


def _busy_scene():
  """Four lanes (y = -6, -2, 2, 6). The SDC (0) and 8 cars within 45 m are
  the controlled set at t = 10; car 9 comes from 90 m behind at +15 m/s and
  passes the SDC at about 5 s; cars 10 and 11 appear 8.5 m from the SDC at
  t = 13 (invalid before, as objects entering a WOMD scene)."""
  xs = (0, 15, -15, 30, -30, 45, -45, 8, -8, -100, 3, -3)
  ys = (-2, -2, -2, 2, 2, -2, -2, 2, 2, 6, 6, 6)
  speeds = (10.0,) * 9 + (25.0, 10.0, 10.0)
  s = make_scene(num_objects=12, num_steps=91, speeds=speeds, ys=ys, xs=xs, half_width=8.0)
  valid = s.log_trajectory.valid.at[jnp.array(NEWCOMERS), :APPEAR].set(False)
  traj = s.log_trajectory.replace(valid=valid)
  return s.replace(log_trajectory=traj, sim_trajectory=traj)


def test_the_scene_would_push_controlled_agents_out():
  """Without `keep`, the nearest-9 set at a later step drops controlled agents:
  the scene tests what it claims."""
  state = _busy_scene()                                           # sim == log
  first, _ = features_lib.select_agents(state.replace(timestep=jnp.int32(START)), CFG.features.max_agents)
  later, _ = features_lib.select_agents(state.replace(timestep=jnp.int32(APPEAR + 2)), CFG.features.max_agents)
  assert not set(np.asarray(first).tolist()) <= set(np.asarray(later).tolist())
  kept, ok = features_lib.select_agents(state.replace(timestep=jnp.int32(APPEAR + 2)),
                                        CFG.features.max_agents, keep=jnp.zeros(12, bool).at[first].set(True))
  assert set(np.asarray(first).tolist()) == set(np.asarray(kept).tolist()) and bool(ok.all())
  assert int(kept[0]) == 0                                        # the SDC stays first


def _actors():
  # Guided plans: the adversarial mode covers the objective mode's path too
  # (the same guided sampler, plus the pursuer chosen at init).
  guided = lambda mode: policy.PolicyConfig(ddim_steps=2, guidance=GuidanceConfig(mode=mode))
  return {
      "cv": (baselines.constant_velocity(baselines.reactive_agents(8)), None),
      "idm": (idm.idm(controlled_fn=baselines.reactive_agents(8)), None),
      "simpl-ar": (simpl_ar.simpl_ar(CFG, simpl_ar.SimplARConfig(sample=True)), "encoder"),
      "pcdiff-warm": (policy.actor(CFG, policy.PolicyConfig(ddim_steps=2, warm_start=True, warm_step=20)),
                      "models"),
      "pcdiff-adversarial": (policy.actor(CFG, guided("adversarial")), "models"),
  }


@pytest.mark.parametrize("name", list(_actors()))
def test_no_controlled_agent_is_lost(name, tiny_models):
  actor, which = _actors()[name]
  params = {"encoder": tiny_models.encoder, "models": tiny_models, None: None}[which]
  cfg = evaluation.EvalConfig(num_steps=NUM_STEPS, metrics=MetricsConfig(max_reactive_agents=8))
  run = evaluation.make_rollout_fn(actor, cfg)
  batch = jax.tree_util.tree_map(lambda a: a[None], _busy_scene())
  final = jax.tree_util.tree_map(lambda a: a[0], run(batch, jax.random.key(0)[None], params))
  controlled, lost = metrics.lost_agents(final, START, NUM_STEPS)
  assert int(controlled.sum()) == 8 and not bool(controlled[0])
  assert int(lost.sum()) == 0, f"{name} lost {np.flatnonzero(np.asarray(lost))}"
  # And so every controlled agent is valid at every simulated step.
  assert bool(jnp.all(final.sim_trajectory.valid[controlled][:, START:START + NUM_STEPS + 1]))
