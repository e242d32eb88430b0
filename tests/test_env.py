"""The functional simulator: reset, step, the lax.scan rollout."""
from __future__ import annotations

import itertools
import pathlib

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene, stack_states
from pcdiff_jax import baselines
from pcdiff_jax.data import womd
from pcdiff_jax.sim import env
from pcdiff_jax.sim.datatypes import Action


def test_reset_matches_waymax_semantics(real_state):
  s = env.reset(real_state)
  s.validate()
  assert int(s.timestep) == 10 and int(s.remaining_timesteps) == 80
  sim_valid = np.asarray(s.sim_trajectory.valid)
  np.testing.assert_array_equal(sim_valid[:, :11], np.asarray(real_state.log_trajectory.valid)[:, :11])
  assert not sim_valid[:, 11:].any()
  np.testing.assert_array_equal(np.asarray(s.current_sim_trajectory.x)[:, 0],
                                np.asarray(real_state.log_trajectory.x)[:, 10])


def test_step_moves_controlled_and_replays_the_rest(scene):
  s = env.reset(scene, init_steps=5)
  controlled = jnp.array([False, True, True, False])
  action = Action(data=jnp.array([[0, 0], [2.0, 0.0], [0, 0], [0, 0]], jnp.float32),
                  valid=jnp.array([[True], [True], [False], [True]]))
  nxt = env.step(s, action, controlled)
  assert int(nxt.timestep) == 5
  log = scene.log_trajectory
  # Uncontrolled: exactly the log.
  for i in (0, 3):
    assert float(nxt.sim_trajectory.x[i, 5]) == float(log.x[i, 5])
  # Controlled with a valid action: the kinematic model (v' = 8 + 0.2).
  np.testing.assert_allclose(float(nxt.sim_trajectory.x[1, 5]), float(log.x[1, 4]) + 0.1 * 8.2, rtol=1e-6)
  np.testing.assert_allclose(float(nxt.sim_trajectory.vel_x[1, 5]), 8.2, rtol=1e-6)
  # Controlled with an invalid action: invalid.
  assert not bool(nxt.sim_trajectory.valid[2, 5])
  assert bool(nxt.object_metadata.is_controlled[1])


def test_rollout_scan_equals_python_loop(scene):
  s = env.reset(scene, init_steps=5)
  actor = baselines.constant_velocity(baselines.reactive_agents(2))
  rng = jax.random.PRNGKey(0)
  out = env.rollout(s, actor, 20, rng)
  actor_state = actor.init(rng, s)
  loop = s
  for k in range(20):
    o = actor.select_action(None, loop, actor_state, jax.random.fold_in(rng, k))
    loop = env.step(loop, o.action, o.is_controlled)
  for a, b in zip(jax.tree_util.tree_leaves(out.final_state), jax.tree_util.tree_leaves(loop)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  assert out.actions.data.shape == (20, 4, 2) and out.is_controlled.shape == (20, 4)
  assert int(out.final_state.timestep) == 24


def test_jit_vmap_batch_and_no_recompiles():
  scenes = [make_scene(speeds=(10.0, 8.0, 0.0, v)) for v in (5.0, 3.0, 1.0)]
  actor = baselines.constant_velocity(baselines.reactive_agents(3))

  @jax.jit
  @chex.assert_max_traces(n=1)
  def run(state, rng):
    return env.rollout(env.reset(state, 5), actor, 20, rng).final_state

  rng = jax.random.PRNGKey(0)
  singles = [run(s, rng) for s in scenes]  # three scenarios, one trace
  batched = jax.jit(jax.vmap(lambda s: env.rollout(env.reset(s, 5), actor, 20, rng).final_state))(
      stack_states(scenes[:2]))
  for i in range(2):
    np.testing.assert_allclose(batched.sim_trajectory.x[i], singles[i].sim_trajectory.x, rtol=1e-6)
  # The state functions also take leading batch dims directly (no vmap).
  direct = env.rollout(env.reset(stack_states(scenes[:2]), 5), actor, 20, rng).final_state
  np.testing.assert_allclose(direct.sim_trajectory.x, batched.sim_trajectory.x, rtol=1e-6)


def test_align_headings_turns_a_sideways_box_to_its_motion_and_keeps_the_rest(scene):
  """Object 1 drives along x with a box heading of 90 degrees (as some converted real scenes
  have it), object 3 reverses (heading 180 degrees), object 2 stands: only object 1's heading
  changes, at every step up to the current one, never in the log."""
  yaw = scene.log_trajectory.yaw.at[1].set(jnp.pi / 2).at[3].set(jnp.pi).at[2].set(1.0)
  log = scene.log_trajectory.replace(yaw=yaw)
  s = env.reset(scene.replace(log_trajectory=log), init_steps=5)
  aligned = env.align_headings(s)
  got = np.asarray(aligned.sim_trajectory.yaw)
  np.testing.assert_allclose(got[1, :5], 0.0, atol=1e-6)
  np.testing.assert_array_equal(got[[0, 2, 3]], np.asarray(s.sim_trajectory.yaw)[[0, 2, 3]])
  np.testing.assert_array_equal(got[1, 5:], np.asarray(s.sim_trajectory.yaw)[1, 5:])
  np.testing.assert_array_equal(np.asarray(aligned.log_trajectory.yaw), np.asarray(log.yaw))
  # The kinematic model now starts it at its logged speed instead of standing.
  from pcdiff_jax.sim import dynamics
  v = lambda st: float(dynamics.states_from_trajectory(st.current_sim_trajectory)[1, 0, dynamics.V])
  assert abs(v(s)) < 1e-5 and abs(v(aligned) - 8.0) < 1e-5
  # A batch of scenes works the same.
  batched = env.align_headings(stack_states([s, s]))
  np.testing.assert_allclose(np.asarray(batched.sim_trajectory.yaw)[:, 1, :5], 0.0, atol=1e-6)


def test_a_simulated_start_is_reset_then_aligned(scene):
  """`env.simulated_start` (where evaluation and the fine-tuning rounds start a rollout) is
  `reset` followed by `align_headings`, or `reset` alone without align."""
  log = scene.log_trajectory.replace(yaw=scene.log_trajectory.yaw.at[1].set(jnp.pi / 2))
  s = scene.replace(log_trajectory=log)
  got = env.simulated_start(s, 5)
  want = env.align_headings(env.reset(s, 5))
  np.testing.assert_array_equal(np.asarray(got.sim_trajectory.yaw), np.asarray(want.sim_trajectory.yaw))
  assert int(got.timestep) == int(want.timestep)
  raw = env.simulated_start(s, 5, align=False)
  np.testing.assert_array_equal(np.asarray(raw.sim_trajectory.yaw), np.asarray(env.reset(s, 5).sim_trajectory.yaw))
  assert float(raw.sim_trajectory.yaw[1, 0]) != float(got.sim_trajectory.yaw[1, 0])


def _cv_second_of_object_1(scene, init_steps: int, **eval_fields) -> float:
  """How far object 1 moves along x in the first second of a constant-velocity rollout through
  the evaluation harness (`evaluation.make_rollout_fn`) with the given EvalConfig fields."""
  from pcdiff_jax import evaluation
  actor = baselines.constant_velocity(baselines.reactive_agents(2))
  cfg = evaluation.EvalConfig(method="cv", num_steps=10, init_steps=init_steps, **eval_fields)
  rngs = jax.random.split(jax.random.PRNGKey(0), 1)
  final = evaluation.make_rollout_fn(actor, cfg)(stack_states([scene]), rngs, None)
  start = init_steps - 1
  return float(final.sim_trajectory.x[0, 1, start + 10] - final.sim_trajectory.x[0, 1, start])


def test_the_evaluation_harness_aligns_headings_for_a_simulated_method_only(scene):
  """Constant velocity (the zero action) drives object 1, logged along x with a sideways box, on
  at its logged 8 m/s once aligned (`EvalConfig.align_headings`), and leaves it standing without."""
  log = scene.log_trajectory.replace(yaw=scene.log_trajectory.yaw.at[1].set(jnp.pi / 2))
  moved = {align: _cv_second_of_object_1(scene.replace(log_trajectory=log), 5, align_headings=align)
           for align in (True, False)}
  np.testing.assert_allclose(moved[True], 8.0, atol=1e-3)
  assert abs(moved[False]) < 1e-3


def _with_current_speeds(scene, current: int, speeds: dict):
  """The scene with the logged vel_x of some objects changed at step `current` only."""
  vel_x = scene.log_trajectory.vel_x
  for obj, v in speeds.items():
    vel_x = vel_x.at[obj, current].set(v)
  return scene.replace(log_trajectory=scene.log_trajectory.replace(vel_x=vel_x))


def test_fit_current_velocity_replaces_only_a_velocity_its_positions_contradict(scene):
  """Every object drives at a constant speed along x. At the current step (7) object 1's
  tracked speed reads 14 m/s against its positions' 8 (replaced by 8), object 3's 6.5 against 5
  (within 2 m/s: kept); object 2's reads 4 against 0 but its track starts at step 4, short of
  0.5 s (kept). Earlier steps and the log keep their values."""
  s = _with_current_speeds(scene, 7, {1: 14.0, 2: 4.0, 3: 6.5})
  s = s.replace(log_trajectory=s.log_trajectory.replace(valid=s.log_trajectory.valid.at[2, :4].set(False)))
  start = env.reset(s, init_steps=8)
  fitted = env.fit_current_velocity(start)
  got = np.asarray(fitted.sim_trajectory.vel_x)
  np.testing.assert_allclose(got[:, 7], [10.0, 8.0, 4.0, 6.5], atol=1e-3)
  np.testing.assert_array_equal(np.asarray(fitted.sim_trajectory.vel_y), np.asarray(start.sim_trajectory.vel_y))
  np.testing.assert_array_equal(got[:, :7], np.asarray(start.sim_trajectory.vel_x)[:, :7])
  np.testing.assert_array_equal(np.asarray(fitted.log_trajectory.vel_x), np.asarray(s.log_trajectory.vel_x))
  batched = env.fit_current_velocity(stack_states([start, start]))
  np.testing.assert_allclose(np.asarray(batched.sim_trajectory.vel_x)[:, :, 7], [got[:, 7]] * 2, atol=1e-6)
  # Too little history for a fit (the current step 3): nothing changes.
  early = env.reset(_with_current_speeds(scene, 3, {1: 14.0}), init_steps=4)
  np.testing.assert_array_equal(np.asarray(env.fit_current_velocity(early).sim_trajectory.vel_x),
                                np.asarray(early.sim_trajectory.vel_x))


def test_the_evaluation_harness_starts_from_the_positions_velocity_unless_told_not_to(scene):
  """Constant velocity drives object 1, whose tracked speed reads 14 m/s at the start against
  its positions' 8, 8 m in a second by default (`EvalConfig.fit_start_velocity`) and 14 m with
  the tracked velocity (`--start-velocity tracked`)."""
  fast = _with_current_speeds(scene, 7, {1: 14.0})
  moved = [_cv_second_of_object_1(fast, 8, fit_start_velocity=fit) for fit in (True, False)]
  np.testing.assert_allclose(moved, [8.0, 14.0], atol=1e-3)


def test_fit_current_velocity_on_the_real_val_scenes():
  """Of the real val scenes' objects with 0.5 s of history, six have a tracked velocity more than
  2 m/s off their positions': record 30's trucks (39.0 -> 35.9 m/s behind one at 30) among them."""
  val = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "womd_real" / "val.scenario.tfrecord"
  if not val.exists():
    pytest.skip(f"real WOMD val scenes not found at {val} (../shared is absent)")
  state = womd.load(str(val), index=30, max_num_objects=None)[0]
  start = env.reset(state)
  fitted = env.fit_current_velocity(start)
  speed = lambda s: np.hypot(np.asarray(s.sim_trajectory.vel_x[:, 10]), np.asarray(s.sim_trajectory.vel_y[:, 10]))
  changed = np.nonzero(speed(start) != speed(fitted))[0]
  assert changed.tolist() == [11, 17, 18]
  np.testing.assert_allclose(speed(start)[18], 39.0, atol=0.05)
  np.testing.assert_allclose(speed(fitted)[18], 35.9, atol=0.05)


def test_align_headings_leaves_real_headings_nearly_as_they_are(real_state):
  """The real record (WOMD's own headings) keeps every heading. The shared val scenes stored in
  degrees (records 3-15) spun when read as radians, and alignment turned every mover of them;
  read in radians they keep nearly all (a few object-steps of near-still movers)."""
  turned = lambda s: int(np.sum(np.asarray(env.align_headings(env.reset(s)).sim_trajectory.yaw)
                                != np.asarray(env.reset(s).sim_trajectory.yaw)))
  assert turned(real_state) == 0
  val = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "womd_real" / "val.scenario.tfrecord"
  if not val.exists():
    pytest.skip(f"real WOMD val scenes not found at {val} (../shared is absent)")
  counts = [turned(s) for s in itertools.islice(womd.iterate(str(val)), 6)]
  assert counts == [0, 0, 0, 3, 0, 2], counts
