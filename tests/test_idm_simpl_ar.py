"""IDM and SIMPL-AR baselines: car following, lane pursuit, joint mode selection."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax.baselines import idm, simpl_ar
from pcdiff_jax.sim import env

CFG = idm.IDMConfig()


def test_idm_acceleration_free_road_and_following():
  free = float(idm.idm_acceleration(jnp.float32(5.0), jnp.float32(jnp.inf), jnp.float32(0.0), CFG))
  assert free == pytest.approx(CFG.max_accel * (1 - (5.0 / CFG.desired_speed) ** 4), rel=1e-5)
  at_speed = float(idm.idm_acceleration(jnp.float32(CFG.desired_speed), jnp.float32(jnp.inf),
                                        jnp.float32(0.0), CFG))
  assert at_speed == pytest.approx(0.0, abs=1e-5)
  closing = float(idm.idm_acceleration(jnp.float32(10.0), jnp.float32(5.0), jnp.float32(0.0), CFG))
  assert closing == pytest.approx(-CFG.max_brake)                   # a stopped car 5 m ahead


def test_idm_finds_the_leader_and_follows_the_lane():
  # Object 3 (x=-30, y=-2, 5 m/s) drives behind the SDC (x=0, y=-2, 10 m/s): 35 m
  # apart at t = 10.
  state = env.reset(make_scene(num_steps=91))
  gap, lead_speed = idm._leader_gap(state, CFG)
  assert float(gap[3]) == pytest.approx(35.0 - 4.5, abs=1e-3)
  assert float(lead_speed[3]) == pytest.approx(10.0, abs=1e-3)
  assert not np.isfinite(float(gap[0])) or float(gap[0]) > 0
  actions = idm.idm_actions(state, CFG)
  # The only lane centre is y = 0: agents at y = -2 steer left (positive yaw rate).
  assert float(actions[0, 1]) > 0 and float(actions[3, 1]) > 0
  out = jax.jit(lambda s: env.rollout(s, idm.idm(), 30, jax.random.key(0)))(state)
  y = np.asarray(out.final_state.sim_trajectory.y[3, 10:41])
  assert abs(y[-1]) < abs(y[0])                                      # converging to the lane


def test_simpl_ar_mode_selection_avoids_a_collision():
  # Two agents, two modes each: both most likely modes collide; agent 1's
  # second mode is free. ICM keeps agent 0's best mode and moves agent 1.
  probs = jnp.array([[0.9, 0.1], [0.6, 0.4]])
  coll = jnp.zeros((2, 2, 2, 2)).at[0, 0, 1, 0].set(5.0).at[1, 0, 0, 0].set(5.0)
  modes = simpl_ar.select_modes(probs, coll, jnp.array([True, True]), simpl_ar.SimplARConfig())
  assert modes.tolist() == [0, 1]
  lonely = simpl_ar.select_modes(probs, jnp.zeros((2, 2, 2, 2)), jnp.array([True, True]),
                                 simpl_ar.SimplARConfig())
  assert lonely.tolist() == [0, 0]


def test_circle_collision_counts():
  t = 4
  xy = jnp.zeros((2, 1, t, 2)).at[1, 0, :, 0].set(jnp.array([1.0, 3.0, 10.0, 10.0]))
  yaw = jnp.zeros((2, 1, t))
  counts = simpl_ar.collision_counts(xy, yaw, jnp.array([4.0, 4.0]), jnp.array([2.0, 2.0]),
                                     jnp.array([True, True]))
  assert counts.shape == (2, 1, 2, 1)
  assert float(counts[0, 0, 0, 0]) == 0 and float(counts[0, 0, 1, 0]) == float(counts[1, 0, 0, 0])
  assert float(counts[0, 0, 1, 0]) > 0                               # overlapping at the first steps
  assert float(counts[0, 0, 1, 0]) == float(simpl_ar.collision_counts(
      xy[:, :, :2], yaw[:, :, :2], jnp.array([4.0, 4.0]), jnp.array([2.0, 2.0]),
      jnp.array([True, True]))[0, 0, 1, 0])                          # none after step 2


def test_idm_ego_drives_the_sdc_while_the_method_drives_the_rest():
  from pcdiff_jax import evaluation
  actor, params = evaluation.make_actor(evaluation.EvalConfig(method="cv", ego="idm"))
  state = env.reset(make_scene(num_steps=91))
  out = jax.jit(lambda s: env.rollout(s, actor, 20, jax.random.key(0), params=params))(state)
  final = out.final_state
  controlled = np.asarray(final.object_metadata.is_controlled)
  assert controlled[0] and controlled[1:4].all()                      # SDC (IDM) + reactive (CV)
  sim_x, log_x = np.asarray(final.sim_trajectory.x[0, 11:31]), np.asarray(final.log_trajectory.x[0, 11:31])
  assert not np.allclose(sim_x, log_x, atol=0.05)                   # the SDC no longer replays its log
  with pytest.raises(ValueError, match="ego"):
    evaluation.make_actor(evaluation.EvalConfig(method="cv", ego="planner"))
