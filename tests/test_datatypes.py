"""Waymax-compatible datatypes: shapes, dtypes, properties, batch dims."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene, stack_states
from pcdiff_jax.sim.datatypes import Action, slice_time, update_time


def test_real_state_fields_match_waymax(real_state):
  s = real_state
  t = s.log_trajectory
  for name in ("x", "y", "z", "vel_x", "vel_y", "yaw", "length", "width", "height"):
    assert getattr(t, name).dtype == jnp.float32 and getattr(t, name).shape == (128, 91)
  assert t.valid.dtype == jnp.bool_ and t.timestamp_micros.dtype == jnp.int32
  md = s.object_metadata
  assert md.ids.dtype == jnp.int32 and md.object_types.dtype == jnp.int32 and md.is_sdc.dtype == jnp.bool_
  assert s.roadgraph_points.types.shape == (30000,) and s.log_traffic_light.state.shape == (16, 91)
  assert s.sdc_paths is None and s.timestep.dtype == jnp.int32
  assert t.xy.shape == (128, 91, 2) and t.bbox_corners.shape == (128, 91, 4, 2)
  np.testing.assert_allclose(t.speed, np.hypot(t.vel_x, t.vel_y), rtol=1e-6)


@pytest.mark.parametrize("batch", [(), (2,), (2, 3)])
def test_batch_dims_and_current_step(batch):
  base = make_scene()
  flat = [base.replace(timestep=jnp.int32(k)) for k in range(int(np.prod(batch)) or 1)]
  state = stack_states(flat) if batch else flat[0]
  if len(batch) == 2:
    state = __import__("jax").tree_util.tree_map(lambda a: a.reshape(batch + a.shape[1:]), state)
  state.validate()
  assert state.shape == batch
  cur = state.current_sim_trajectory
  assert cur.shape == batch + (4, 1)
  expected = np.asarray(state.timestep) * 0.1 * 10.0  # agent 0: x = 10 m/s * t
  np.testing.assert_allclose(np.asarray(cur.x)[..., 0, 0], expected, rtol=1e-5, atol=1e-5)


def test_update_time_writes_one_column():
  s = make_scene()
  new = slice_time(s.log_trajectory, jnp.int32(3)).replace(x=jnp.full((4, 1), 99.0))
  out = update_time(s.log_trajectory, jnp.int32(7), new)
  assert (np.asarray(out.x)[:, 7] == 99.0).all()
  np.testing.assert_array_equal(np.delete(np.asarray(out.x), 7, 1), np.delete(np.asarray(s.log_trajectory.x), 7, 1))


def test_validate_rejects_wrong_dtypes_and_shapes():
  s = make_scene()
  with pytest.raises(ValueError, match="Trajectory.x has dtype"):
    s.replace(log_trajectory=s.log_trajectory.replace(x=s.log_trajectory.x.astype(jnp.int32))).validate()
  with pytest.raises(ValueError, match="disagree on shape"):
    s.log_trajectory.replace(y=s.log_trajectory.y[:, :3]).validate()
  with pytest.raises(ValueError, match="more than one SDC"):
    s.object_metadata.replace(is_sdc=jnp.ones(4, bool)).validate()
  with pytest.raises(ValueError, match="Action.valid has shape"):
    Action(data=jnp.zeros((4, 2)), valid=jnp.zeros((4,), bool)).validate()
