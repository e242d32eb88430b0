"""Route IDM: each object on its logged path, IDM speed, still objects held."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax import baselines
from pcdiff_jax.baselines import route as idm_route
from pcdiff_jax.sim import env


def _scene():
  """SDC (log replay) stopped at x = 40 on y = -2; object 3 drives at 10 m/s
  towards it on the same line (its log drives through it); object 2 stands
  still off the road; object 1 drives a left-hand arc (R = 40 m, 8 m/s) whose
  log has a gap at step 50."""
  state = make_scene(num_steps=91, speeds=(0.0, 8.0, 0.0, 10.0), xs=(40.0, 0.0, 10.0, -10.0))
  log = state.log_trajectory
  t = np.arange(91) * 0.1
  w = 8.0 / 40.0
  arc = dict(x=40.0 * np.sin(w * t), y=2.0 + 40.0 * (1 - np.cos(w * t)), yaw=w * t,
             vel_x=8.0 * np.cos(w * t), vel_y=8.0 * np.sin(w * t))
  log = log.replace(**{k: getattr(log, k).at[1].set(jnp.asarray(v, jnp.float32)) for k, v in arc.items()},
                    valid=log.valid.at[1, 50].set(False))
  return env.reset(state.replace(log_trajectory=log, sim_trajectory=log))


def test_route_points_follow_the_log_and_extend_past_its_end():
  log = _scene().log_trajectory
  route = idm_route.logged_route(log)
  assert route.last.tolist() == [90, 89, 90, 90]                      # object 1 lost step 50
  s = route.s[3]                                                      # 10 m/s: 1 m per step
  np.testing.assert_allclose(np.asarray(s[:4]), [0.0, 1.0, 2.0, 3.0], atol=1e-4)
  xy, heading = idm_route.route_points(route, jnp.array([[0.0, 0.0]] * 3 + [[2.5, 95.0]]))
  np.testing.assert_allclose(np.asarray(xy[3]), [[-7.5, -2.0], [85.0, -2.0]], atol=1e-3)  # past the end: straight on
  np.testing.assert_allclose(np.asarray(heading[3]), [0.0, 0.0], atol=1e-6)


def test_route_idm_stops_behind_a_stopped_car_holds_still_objects_and_follows_free_paths():
  state = _scene()
  actor = baselines.idm_route(controlled_fn=baselines.reactive_agents(3))
  out = jax.jit(lambda s: env.rollout(s, actor, 80, jax.random.key(0)))(state)
  sim, log = out.final_state.sim_trajectory, state.log_trajectory
  assert np.asarray(out.final_state.object_metadata.is_controlled).tolist() == [False, True, True, True]
  assert bool(sim.valid[:, 10:].all())
  # Object 3 stops behind the stopped SDC, never touching it (boxes 4.5 m long).
  x3 = np.asarray(sim.x[3, 10:])
  gap = 40.0 - x3 - 4.5
  assert gap.min() > 1.0 and gap[-1] < 4.0
  assert float(sim.speed[3, -1]) < 0.5 and gap[-1] > 2.0            # IDM creeps up to s0 = 2 m
  np.testing.assert_allclose(np.asarray(sim.y[3, 10:]), -2.0, atol=1e-4)
  # Object 2 (0 m/s at the start) stays exactly where it was.
  np.testing.assert_allclose(np.asarray(sim.x[2, 10:]), float(log.x[2, 10]), atol=1e-5)
  np.testing.assert_allclose(np.asarray(sim.y[2, 10:]), float(log.y[2, 10]), atol=1e-5)
  # Object 1 drives its logged arc at its logged speed.
  err = np.hypot(np.asarray(sim.x[1, 11:] - log.x[1, 11:]), np.asarray(sim.y[1, 11:] - log.y[1, 11:]))
  assert err.max() < 0.05


def test_route_idm_is_the_rollout_idm_and_the_lane_idm_is_kept():
  from pcdiff_jax import evaluation
  assert evaluation.METHODS["idm"](8).name == "idm"
  assert evaluation.METHODS["idm-lane"](8).name == "idm-lane"
  cfg = idm_route.IDMRouteConfig()
  rs = idm_route.init_route_state(_scene(), jnp.array([False, True, True, True]), cfg)
  assert np.asarray(rs.held).tolist() == [False, False, True, False]
  np.testing.assert_allclose(np.asarray(rs.desired[1:]), [8.0, 1e-3, 10.0], rtol=1e-5)
  assert float(rs.progress[3]) == pytest.approx(10.0, abs=1e-3)     # its 11th logged point: 10 m on
