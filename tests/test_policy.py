"""The closed-loop policy: actor contract, one fused scan, no recompiles, replanning."""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene, stack_states
from pcdiff_jax import evaluation, policy
from pcdiff_jax.config import get_config
from pcdiff_jax.model import denoiser as denoiser_lib
from pcdiff_jax.model import encoder, planner
from pcdiff_jax.sim import dynamics, env, geometry
from pcdiff_jax.training import data as data_lib
from pcdiff_jax.training import diffusion_stage

CFG = get_config("tiny")
# One sample per plan where a test is about something else: sample selection (the default's 4
# samples and its road field) has its own tests, and the closed-loop test runs the defaults.


@pytest.fixture(scope="module")
def models(tiny_models):
  return tiny_models


def _scenes(speeds_list):
  return stack_states([make_scene(num_steps=91, speeds=s) for s in speeds_list])


def test_closed_loop_is_one_program_without_recompiles(models):
  actor = policy.actor(CFG, policy.PolicyConfig(ddim_steps=2))
  cfg = evaluation.EvalConfig(num_steps=6)
  run = evaluation.make_rollout_fn(actor, cfg)
  rngs = jax.random.split(jax.random.key(0), 2)
  first = run(_scenes([(10.0, 8.0, 0.0, 5.0), (6.0, 7.0, 1.0, 3.0)]), rngs, models)
  second = run(_scenes([(12.0, 2.0, 0.0, 9.0), (4.0, 4.0, 4.0, 4.0)]), rngs, models)
  assert run._cache_size() == 1                                    # same padded size: one compile
  traj = second.sim_trajectory
  steps = slice(11, 17)
  assert bool(jnp.all(jnp.isfinite(traj.x[:, :, steps])))
  # The SDC (object 0) follows its log; the reactive agents are the policy's.
  np.testing.assert_allclose(np.asarray(traj.x[:, 0, steps]),
                             np.asarray(second.log_trajectory.x[:, 0, steps]), atol=1e-5)
  controlled = np.asarray(second.object_metadata.is_controlled)
  assert not controlled[:, 0].any() and controlled[:, 1:].all()
  assert not np.allclose(np.asarray(traj.x[:, 1:, steps]), np.asarray(second.log_trajectory.x[:, 1:, steps]))
  del first


def test_replanning_interval_and_single_step(models):
  state = env.reset(make_scene(num_steps=91))
  act = policy.actor(CFG, policy.PolicyConfig(select_samples=1, ddim_steps=1, replan_every=3))
  ps = act.init(jax.random.key(0), state)
  select = jax.jit(act.select_action)
  ages, plans = [], []
  for k in range(5):
    out = select(models, state, ps, jax.random.key(k))
    ps = out.actor_state
    ages.append(int(ps.age))
    plans.append(np.asarray(ps.plan))
    state = env.step(state, out.action, out.is_controlled)
  assert ages == [1, 2, 3, 1, 2]
  np.testing.assert_array_equal(plans[0], plans[2])                # kept between replans
  assert not np.array_equal(plans[2], plans[3])                    # a new plan at step 3
  action, controlled = jax.jit(lambda s, r: policy.step(s, models, CFG, r))(state, jax.random.key(9))
  assert action.data.shape == (4, 2) and action.valid.shape == (4, 1)
  assert not bool(controlled[0]) and bool(jnp.all(jnp.isfinite(action.data)))
  with pytest.raises(ValueError, match="replan_every"):
    policy.actor(CFG, policy.PolicyConfig(replan_every=0))


def test_consistent_noise_makes_the_plan_a_function_of_the_scene(models):
  """With the rollout's noise (consistent_noise), the step's rng does not
  change the plan (eta = 0); without it, it does."""
  state = env.reset(make_scene(num_steps=91))
  pcfg = policy.PolicyConfig(select_samples=1, ddim_steps=1, consistent_noise=True)
  ps = policy.actor(CFG, pcfg).init(jax.random.key(0), state)
  plan = jax.jit(lambda r, n: policy.plan_actions(models, state, CFG, pcfg, r, -1, n)[0])
  a, b = plan(jax.random.key(1), ps.noise), plan(jax.random.key(2), ps.noise)
  np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  fresh = jax.jit(lambda r: policy.plan_actions(models, state, CFG, pcfg, r)[0])
  assert not np.array_equal(np.asarray(fresh(jax.random.key(1))), np.asarray(fresh(jax.random.key(2))))


def test_rollout_cli_needs_a_checkpoint_for_learned_methods(tmp_path, womd_path):
  from experiments import rollout
  with pytest.raises(SystemExit):
    rollout.main(["--scenarios", womd_path, "--method", "pcdiff", "--out", str(tmp_path)])
  assert rollout.main(["--scenarios", womd_path, "--method", "pcdiff", "--checkpoint",
                       str(tmp_path / "nothing"), "--out", str(tmp_path / "o")]) == 2


def test_guided_closed_loop_runs_and_changes_the_plans(models):
  """Objective and adversarial guidance inside the fused closed loop: finite,
  different plans from the unguided ones, the pursuer chosen at init."""
  from pcdiff_jax.model.guidance import GuidanceConfig
  states = _scenes([(10.0, 8.0, 0.0, 5.0)])
  rngs = jax.random.split(jax.random.key(0), 1)
  cfg = evaluation.EvalConfig(num_steps=3)
  finals, ends = {}, {}
  for mode in ("none", "objective", "adversarial"):
    g = GuidanceConfig(mode=mode, eta=0.5, w_pursue=10.0, field_size=64, max_edge_points=512)
    # Cold plans: a smaller program (warm starts under guidance: tests/test_controlled_set.py).
    actor = policy.actor(CFG, policy.PolicyConfig(select_samples=1, ddim_steps=2, warm_start=False, guidance=g))
    ends[mode] = evaluation.make_rollout_fn(actor, cfg)(states, rngs, models)
    finals[mode] = ends[mode].sim_trajectory
    assert bool(jnp.all(jnp.isfinite(finals[mode].x[:, :, 11:14])))
  # Adversarial runs are scored for the ego-adversary pair, and unguided ones on request.
  from pcdiff_jax import metrics as metrics_lib
  for mode, extra in (("adversarial", {"guidance": g}), ("none", {"score_adversary": True})):
    score_cfg = evaluation.EvalConfig(num_steps=3, metrics=CFG.metrics, **extra)
    scores = evaluation.make_score_fn(score_cfg)(ends[mode])
    summary = metrics_lib.aggregate(jax.tree_util.tree_map(lambda a: np.asarray(a)[:, None], scores))
    assert summary["num_pairs"] == 1 and np.isfinite(summary["min_distance"])
  for mode in ("objective", "adversarial"):
    assert not np.allclose(np.asarray(finals[mode].x[:, 1:, 11:14]), np.asarray(finals["none"].x[:, 1:, 11:14]))
  state = env.reset(make_scene(num_steps=91, speeds=(10.0, 8.0, 0.0, 5.0)))
  ps = policy.actor(CFG, policy.PolicyConfig(guidance=GuidanceConfig(mode="adversarial", field_size=32))).init(
      jax.random.key(0), state)
  assert int(ps.adversary) in (1, 2, 3)                            # a reactive vehicle, not the SDC
  with pytest.raises(ValueError, match="mode"):
    policy.actor(CFG, policy.PolicyConfig(guidance=GuidanceConfig(mode="chaos")))


def test_simpl_ar_and_idm_run_in_the_same_closed_loop(models):
  from pcdiff_jax.baselines import idm, simpl_ar
  cfg = evaluation.EvalConfig(num_steps=3)
  states = _scenes([(10.0, 8.0, 0.0, 5.0)])
  rngs = jax.random.split(jax.random.key(0), 1)
  for actor, params in ((simpl_ar.simpl_ar(CFG), models.encoder), (idm.idm(), None)):
    final = evaluation.make_rollout_fn(actor, cfg)(states, rngs, params)
    traj = final.sim_trajectory
    assert bool(jnp.all(jnp.isfinite(traj.x[:, :, 11:14])))
    assert bool(final.object_metadata.is_controlled[0, 1]) and not bool(final.object_metadata.is_controlled[0, 0])


def test_controlled_agents_are_the_scored_agents(real_state):
  """The learned policy controls the agents its encoder sees minus the SDC;
  the metrics score the 64 nearest the SDC: with max_agents = 65 (the SDC +
  64) the two sets are the same on the real sample (73 valid objects)."""
  from pcdiff_jax import metrics as metrics_lib
  cfg = get_config("cpu")
  state = env.reset(real_state)
  controlled = np.asarray(policy.reactive_set(state, cfg))
  scored = np.asarray(metrics_lib.evaluated_agents(state, 10, cfg.metrics.max_reactive_agents))
  assert controlled.sum() == 64
  np.testing.assert_array_equal(controlled, scored)


def test_track_execution_follows_the_planned_path(models):
  state = env.reset(make_scene(num_steps=91))
  cur = state.current_sim_trajectory
  t = (jnp.arange(CFG.encoder.horizon) + 1.0) * 0.1
  ahead = cur.xy[:, 0][:, None] + cur.vel_xy[:, 0][:, None] * t[None, :, None]       # keep going
  valid = np.asarray(cur.valid[:, 0])
  np.testing.assert_allclose(np.asarray(policy.execution._track(state, ahead, 0, 5, CFG))[valid], 0.0, atol=1e-3)
  left = geometry.unit(cur.yaw[:, 0] + np.pi / 2)
  bend = ahead + 0.5 * t[None, :, None] ** 2 * left[:, None]                         # drifting left
  moving = valid & (np.linalg.norm(np.asarray(cur.vel_xy[:, 0]), axis=-1) > 1.0)
  assert (np.asarray(policy.execution._track(state, bend, 0, 5, CFG))[moving, 1] > 0).all()
  act = policy.actor(CFG, policy.PolicyConfig(select_samples=1, ddim_steps=1, replan_every=2, execute="track"))
  ps = act.init(jax.random.key(0), state)
  for k in range(3):
    out = jax.jit(act.select_action)(models, state, ps, jax.random.key(k))
    ps = out.actor_state
    assert bool(jnp.all(jnp.isfinite(out.action.data)))
    state = env.step(state, out.action, out.is_controlled)
  assert float(jnp.abs(ps.path[1:]).sum()) > 0                    # world-frame plan kept
  with pytest.raises(ValueError, match="execute"):
    policy.actor(CFG, policy.PolicyConfig(execute="teleport"))


def test_encoder_history_hides_all_but_the_last_steps_from_the_encoder_only(models):
  """`encoder_history=k`: the proposals are the encoder's on the last k history
  steps; the features the rest of the policy reads keep the whole history."""
  from pcdiff_jax.policy import planning
  state = env.reset(make_scene(num_steps=91))
  pcfg = lambda k: policy.PolicyConfig(select_samples=1, still_gate=(0.0, 0.0), encoder_history=k)
  run = jax.jit(lambda k: planning.encode(models, state, CFG, pcfg(k)), static_argnums=0)
  full, cut = run(0), run(1)
  valid = np.asarray(full.batched.agent_history_valid)
  assert valid[..., :-1].any()
  np.testing.assert_array_equal(np.asarray(cut.feats.agent_history_valid), np.asarray(full.feats.agent_history_valid))
  masked = planning.recent_history(full.batched, 1)
  assert not np.asarray(masked.agent_history_valid)[..., :-1].any()
  np.testing.assert_array_equal(np.asarray(masked.agent_history_valid)[..., -1], valid[..., -1])
  want = jax.jit(lambda f: planner.condition(models.encoder, models.stats, f, CFG))(masked)
  np.testing.assert_allclose(np.asarray(cut.cond.proposals), np.asarray(want.proposals), rtol=1e-4, atol=1e-3)
  assert not np.allclose(np.asarray(cut.cond.proposals), np.asarray(full.cond.proposals))
  assert planning.recent_history(full.batched, 0) is full.batched


def test_prior_centred_on_the_top_mode(models):
  state = env.reset(make_scene(num_steps=91))
  from pcdiff_jax.model import features as features_lib
  feats = jax.jit(lambda st: jax.tree_util.tree_map(lambda a: a[None], features_lib.scene_features(st, CFG.features)))(state)
  cond, top = jax.jit(lambda f: (lambda c: (c, planner.centre_on_top_mode(c)))(
      planner.condition(models.encoder, models.stats, f, CFG)))(feats)
  best = np.asarray(jnp.argmax(cond.probs, -1))[0]
  props = np.asarray(cond.proposals)[0]
  np.testing.assert_allclose(np.asarray(top.mu)[0], props[np.arange(len(best)), best])
  np.testing.assert_array_equal(np.asarray(top.sigma), np.asarray(cond.sigma))
  pcfg = policy.PolicyConfig(select_samples=1, ddim_steps=1, prior_centre="top1")
  plan = jax.jit(lambda r: policy.plan_actions(models, state, CFG, pcfg, r)[0])(jax.random.key(0))
  assert bool(jnp.all(jnp.isfinite(plan)))
  with pytest.raises(ValueError, match="prior_centre"):
    policy.actor(CFG, policy.PolicyConfig(prior_centre="median"))
  # prior_spread "weighted": the same proposals, weighted by the encoder's probabilities.
  from pcdiff_jax.model import diffusion
  weighted = lambda spread: dataclasses.replace(CFG, diffusion=dataclasses.replace(CFG.diffusion, prior_spread=spread))
  cond_w = jax.jit(lambda f: planner.condition(models.encoder, models.stats, f, weighted("weighted")))(feats)
  mu, sigma = diffusion.prior_from_proposals(cond.proposals, CFG.diffusion.eps_sigma, cond.probs)
  np.testing.assert_allclose(np.asarray(cond_w.mu), np.asarray(mu), atol=1e-5)
  np.testing.assert_allclose(np.asarray(cond_w.sigma), np.asarray(sigma), atol=1e-5)
  assert not np.allclose(np.asarray(cond_w.sigma), np.asarray(cond.sigma))
  with pytest.raises(ValueError, match="prior_spread"):
    planner.condition(models.encoder, models.stats, feats, weighted("median"))


def test_warm_start_advances_the_previous_plan(models):
  plan = jnp.arange(2 * 5 * 2, dtype=jnp.float32).reshape(2, 5, 2)       # (O, T, 2)
  out = np.asarray(policy.advance_plan(plan, jnp.int32(2)))
  np.testing.assert_array_equal(out[:, :3], np.asarray(plan[:, 2:]))
  np.testing.assert_array_equal(out[:, 3:], 0.0)                        # the freed tail holds
  np.testing.assert_array_equal(np.asarray(policy.advance_plan(plan, jnp.int32(0))), np.asarray(plan))
  # In closed loop: the first plan is cold, the next ones warm; one program.
  state = env.reset(make_scene(num_steps=91))
  pcfg = policy.PolicyConfig(select_samples=1, ddim_steps=2, warm_start=True, warm_step=0, warm_ddim_steps=1)
  act = policy.actor(CFG, pcfg)
  ps = act.init(jax.random.key(0), state)
  select = jax.jit(act.select_action)
  first = select(models, state, ps, jax.random.key(1))
  state2 = env.step(state, first.action, first.is_controlled)
  second = select(models, state2, first.actor_state, jax.random.key(2))
  assert select._cache_size() == 1
  # warm_step 0: the new plan is the old one advanced by a step, through the latent projection.
  controlled = np.asarray(first.actor_state.controlled)
  old = np.asarray(policy.advance_plan(first.actor_state.plan, jnp.int32(1)))[controlled]
  new = np.asarray(second.actor_state.plan)[controlled]
  cold = jax.jit(lambda s, r: policy.plan_actions(models, s, CFG, policy.PolicyConfig(select_samples=1, ddim_steps=2), r)[0])(
      state2, jax.random.key(2))
  assert np.abs(new - old).mean() < np.abs(np.asarray(cold)[controlled] - old).mean()
  with pytest.raises(ValueError, match="warm_ddim_steps"):
    policy.actor(CFG, policy.PolicyConfig(warm_start=True, warm_step=1, warm_ddim_steps=3))


def test_temporal_ensemble_averages_the_plans_made_for_each_step(models):
  previous = jnp.ones((3, 5, 2))
  new = jnp.zeros((3, 5, 2))
  had = jnp.array([True, True, False])                           # agent 2 had no plan
  out = np.asarray(jax.jit(policy.ensemble_plans)(
      previous, had, jnp.int32(2), new, jnp.array([True, False, True]), jnp.array([0.75, 0.25])))
  np.testing.assert_allclose(out[0, :3], [[0.75, 0.25]] * 3)     # the steps both plans cover, per channel
  np.testing.assert_array_equal(out[0, 3:], 0.0)                 # past the previous plan's end
  np.testing.assert_array_equal(out[1:], 0.0)                    # no new plan / no previous plan
  # In closed loop: the executed action is the ensemble's, replanning every step.
  state = env.reset(make_scene(num_steps=91))
  pcfg = policy.PolicyConfig(select_samples=1, ddim_steps=2, temporal_ensemble=(0.5, 0.5), jerk_limit=(0.0, 0.0),
                             stop_hold=False, still_gate=(0.0, 0.0), max_curvature=0.0, replan_every=1)
  act = policy.actor(CFG, pcfg)
  select = jax.jit(act.select_action)
  first = select(models, state, act.init(jax.random.key(0), state), jax.random.key(1))
  state2 = env.step(state, first.action, first.is_controlled)
  second = select(models, state2, first.actor_state, jax.random.key(2))
  assert select._cache_size() == 1
  controlled = np.asarray(first.actor_state.controlled)
  fresh = jax.jit(lambda s, ps, r: policy.plan_actions(
      models, s, CFG, dataclasses.replace(pcfg, temporal_ensemble=(0.0, 0.0)), r, controlled=ps.controlled,
      warm=policy.WarmStart(actions=policy.advance_plan(ps.plan, jnp.int32(1)),
                            has=ps.plan_valid & ps.controlled))[0])(state2, first.actor_state, jax.random.key(2))
  expect = 0.5 * np.asarray(first.actor_state.plan)[:, 1] + 0.5 * np.asarray(fresh)[:, 0]
  # Two programs compiled apart round differently (XLA fuses them differently): 1e-4, not exact.
  np.testing.assert_allclose(np.asarray(second.action.data)[controlled], expect[controlled], atol=1e-4)
  with pytest.raises(ValueError, match="temporal_ensemble"):
    policy.actor(CFG, policy.PolicyConfig(temporal_ensemble=(1.0, 0.0)))


def test_jerk_limit_moves_the_executed_acceleration_by_a_bounded_step():
  from pcdiff_jax.sim.datatypes import Action
  state = env.reset(make_scene(num_steps=91))
  dt = CFG.kinematics.dt
  np.testing.assert_allclose(np.asarray(policy.executed_accel(state, dt)), 0.0, atol=1e-4)   # the log's constant speeds
  applied = jnp.array([[0.0, 0.0], [1.5, 0.0], [-2.0, 0.1], [0.5, 0.0]])
  moved = env.step(state, Action(data=applied, valid=jnp.ones((4, 1), bool)), jnp.array([False, True, True, True]))
  np.testing.assert_allclose(np.asarray(policy.executed_accel(moved, dt))[1:], [1.5, -2.0, 0.5], atol=1e-3)
  wanted = jnp.array([[0.0, 0.0], [5.0, 0.2], [-8.0, 0.0], [0.4, -0.1]])
  last = policy.executed_accel(moved, dt)
  limited = np.asarray(jax.jit(lambda a, l: policy.limit_jerk(a, l, (2.0, 10.0), dt))(wanted, last))
  # Up by at most 2 m/s^3 x 0.1 s, down by at most 10 x 0.1; a small change and the yaw rates pass.
  np.testing.assert_allclose(limited[1:, 0], [1.5 + 0.2, -2.0 - 1.0, 0.4], atol=1e-3)
  np.testing.assert_array_equal(limited[:, 1], np.asarray(wanted)[:, 1])
  one_sided = np.asarray(policy.limit_jerk(wanted, last, (0.0, 10.0), dt))
  assert abs(one_sided[1, 0] - 5.0) < 1e-6                       # rise 0: no limit upwards
  # No executed acceleration yet (NaN, a rollout's first step): the plan's passes.
  free = np.asarray(policy.limit_jerk(wanted, jnp.full((4,), jnp.nan), (2.0, 10.0), dt))
  np.testing.assert_array_equal(free, np.asarray(wanted))
  with pytest.raises(ValueError, match="jerk_limit"):
    policy.actor(CFG, policy.PolicyConfig(jerk_limit=(-1.0, 0.0)))


def test_braking_stops_at_standstill_instead_of_reversing(models):
  """stop_hold: a forward-moving or stopped agent's braking ends at v = 0 (no backing up from a
  brake); an agent that really reverses keeps its action; the yaw rate is untouched."""
  from pcdiff_jax.sim import dynamics
  from pcdiff_jax.sim.datatypes import Action
  state = env.reset(make_scene(num_steps=91, speeds=(10.0, 0.3, 0.0, -2.0)))
  dt = CFG.kinematics.dt
  wanted = jnp.array([[-2.0, 0.1], [-5.0, 0.2], [-1.0, 0.3], [-1.0, 0.0]])
  held = np.asarray(jax.jit(lambda s, a: policy.hold_at_stop(s, a, dt))(state, wanted))
  np.testing.assert_allclose(held[:, 0], [-2.0, -3.0, 0.0, -1.0], atol=1e-5)
  np.testing.assert_array_equal(held[:, 1], np.asarray(wanted)[:, 1])
  moved = env.step(state, Action(data=jnp.asarray(held), valid=jnp.ones((4, 1), bool)), jnp.ones(4, bool))
  speed = np.asarray(dynamics.states_from_trajectory(moved.current_sim_trajectory))[:, 0, dynamics.V]
  np.testing.assert_allclose(speed, [9.8, 0.0, 0.0, -2.1], atol=1e-4)
  # In closed loop no agent that started at v >= 0 ever backs up.
  act = policy.actor(CFG, policy.PolicyConfig(ddim_steps=2, select_samples=1, stop_hold=True))
  select = jax.jit(act.select_action)
  state = env.reset(make_scene(num_steps=91, speeds=(10.0, 0.0, 0.0, 0.5)))
  ps = act.init(jax.random.key(0), state)
  for k in range(6):
    out = select(models, state, ps, jax.random.key(k))
    ps = out.actor_state
    state = env.step(state, out.action, out.is_controlled)
    speed = np.asarray(dynamics.states_from_trajectory(state.current_sim_trajectory))[:, 0, dynamics.V]
    assert np.all(speed > -policy.STOPPED_REVERSE_SPEED), speed
  assert select._cache_size() == 1


def test_sample_selection_keeps_the_least_colliding_joint_plan(models):
  from pcdiff_jax.model import features as features_lib
  from pcdiff_jax.model import guidance as guidance_lib
  from pcdiff_jax.model import joint_selection
  from pcdiff_jax.sim.datatypes import ObjectType
  state = env.reset(make_scene(num_steps=91))
  feats = jax.jit(lambda st: features_lib.scene_features(st, CFG.features))(state)
  s = 3
  batched = jax.tree_util.tree_map(lambda a: jnp.repeat(a[None], s, 0), feats)
  cond = jax.jit(lambda b: planner.condition(models.encoder, models.stats, b, CFG))(batched)
  y0 = 3.0 * jax.random.normal(jax.random.key(0), cond.mu.shape)          # widely spread plans
  keep = jnp.arange(feats.agent_valid.shape[0]) == 0
  # A small road field keeps the test's compiles short; the policy's default is 256 x 256.
  g = guidance_lib.GuidanceConfig(field_size=64)

  @functools.partial(jax.jit, static_argnums=1)
  def candidates(road, stride=1):
    """Every candidate pair's overlaps (A, S, A, S) and each candidate's J_map (A, S)."""
    states = planner.decode_states(models.stats, cond, y0, CFG)[..., :30:stride, :]
    xy, yaw = planner.to_scene(states, batched)
    length, width = planner.agent_size(feats)
    coll = joint_selection.collision_counts(jnp.moveaxis(xy, 0, 1), jnp.moveaxis(yaw, 0, 1),
                                            length, width, feats.agent_valid)
    agents = guidance_lib.Agents(length=length, width=width, valid=feats.agent_valid,
                                 vehicle=feats.agent_types == ObjectType.VEHICLE,
                                 pursuer=jnp.int32(-1), evader=jnp.int32(-1))
    return coll, guidance_lib.map_cost(xy, yaw, agents, road, g).T

  select = jax.jit(lambda road, weight, stride=1: policy.select_sample(
      y0, models, cond, batched, CFG, 30, keep, road, weight, g, stride), static_argnums=(1, 2))
  road = policy.road_for(state, policy.PolicyConfig(select_samples=s, select_map_weight=1.0, guidance=g))
  assert road.values.shape[-1] == g.field_size                    # a real field, not the placeholder
  road = jax.tree_util.tree_map(lambda a: a[None], road.in_frame(feats.scene_xy, feats.scene_yaw))
  coll, cost = (np.asarray(a) for a in candidates(road))
  overlaps = lambda c: float(coll[np.arange(len(c))[:, None], c[:, None], np.arange(len(c))[None], c[None]].sum())

  chosen = select(road, 0.0)
  assert chosen.shape == (1,) + y0.shape[1:]
  choice = np.asarray(jnp.argmax(jnp.all(chosen == y0, -1), 0))          # (A,) the sample each agent kept
  assert int(choice[0]) == 0                                              # the SDC keeps sample 0
  assert overlaps(choice) <= overlaps(np.zeros_like(choice))
  # select_stride: overlaps counted at every 3rd step of the lookahead, same guarantee on those.
  coll = np.asarray(candidates(road, 3)[0])
  choice = np.asarray(jnp.argmax(jnp.all(select(road, 0.0, 3) == y0, -1), 0))
  assert int(choice[0]) == 0 and overlaps(choice) <= overlaps(np.zeros_like(choice))
  # select_held_still: a held agent is scored standing at its start in every sample, and the
  # others' choices carry the same guarantee against that.
  held = jnp.arange(feats.agent_valid.shape[0]) == 1
  states = planner.decode_states(models.stats, cond, y0, CFG)[..., :30, :]
  states = jnp.where(held[None, :, None, None], 0.0, states)
  xy, yaw = planner.to_scene(states, batched)
  coll = np.asarray(joint_selection.collision_counts(jnp.moveaxis(xy, 0, 1), jnp.moveaxis(yaw, 0, 1),
                                                     *planner.agent_size(feats), feats.agent_valid))
  chosen_held = jax.jit(lambda road: policy.select_sample(y0, models, cond, batched, CFG, 30, keep, road,
                                                          0.0, g, 1, 0, held))(road)
  choice = np.asarray(jnp.argmax(jnp.all(chosen_held == y0, -1), 0))
  assert int(choice[0]) == 0 and overlaps(choice) <= overlaps(np.zeros_like(choice))
  assert np.all(coll[1] == coll[1][:1])          # the held agent's samples are one and the same
  # Equally likely candidates without overlaps: everyone keeps sample 0.
  free = joint_selection.iterated_conditional_modes(jnp.zeros((4, 3)), jnp.zeros((4, 3, 4, 3)),
                                                    jnp.ones(4, bool), 1.0, 2, jnp.arange(4))
  assert free.tolist() == [0, 0, 0, 0]
  # With a map term (select_map_weight) that dwarfs the overlap counts, each agent keeps its
  # sample that leaves the road least, on the road field the policy builds for it.
  choice = np.asarray(jnp.argmax(jnp.all(select(road, 1e6) == y0, -1), 0))
  assert choice[0] == 0              # the SDC keeps sample 0 (here its worst on the map)
  ranked = np.sort(cost, -1)
  clear = np.asarray(feats.agent_valid & ~keep) & (ranked[:, 1] - ranked[:, 0] > 0.1)
  assert clear.sum() >= 1
  np.testing.assert_array_equal(choice[clear], np.argmin(cost, -1)[clear])
  # In closed loop (with consistent noise: each sample's its own draw): one program, finite actions.
  act = policy.actor(CFG, policy.PolicyConfig(ddim_steps=2, select_samples=s, consistent_noise=True, guidance=g))
  select = jax.jit(act.select_action)
  ps = act.init(jax.random.key(0), state)
  for k in range(2):
    out = select(models, state, ps, jax.random.key(k))
    ps = out.actor_state
    assert bool(jnp.all(jnp.isfinite(out.action.data)))
    state = env.step(state, out.action, out.is_controlled)
  assert select._cache_size() == 1
  with pytest.raises(ValueError, match="select_samples"):
    policy.actor(CFG, policy.PolicyConfig(select_samples=0))
  with pytest.raises(ValueError, match="select_stride"):
    policy.actor(CFG, policy.PolicyConfig(select_stride=31))
  with pytest.raises(ValueError, match="select_neighbours"):
    policy.actor(CFG, policy.PolicyConfig(select_neighbours=-1))


def test_wheeled_objects_turn_only_by_moving():
  """max_curvature: a vehicle's or cyclist's yaw rate is bounded by max_curvature x its speed
  after this step's acceleration (a parked car does not spin in place); a pedestrian keeps its
  yaw rate; in closed loop a stopped car held by a gate keeps its heading exactly."""
  from pcdiff_jax.sim.datatypes import ObjectType
  state = env.reset(make_scene(num_objects=4, num_steps=91, speeds=(10.0, 0.0, 2.0, 0.0)))
  types = jnp.array([ObjectType.VEHICLE, ObjectType.VEHICLE, ObjectType.CYCLIST, ObjectType.PEDESTRIAN])
  state = state.replace(object_metadata=state.object_metadata.replace(object_types=types))
  dt = CFG.kinematics.dt
  wanted = jnp.array([[0.0, 0.5], [1.0, 0.5], [0.0, -0.9], [0.0, 0.7]])
  out = np.asarray(jax.jit(lambda s, a: policy.limit_curvature(s, a, 0.2, dt))(state, wanted))
  # Bounds 0.2 x |v + a dt|: 2.0 (passes), 0.02, 0.4 (clipped, sign kept); the pedestrian passes.
  np.testing.assert_allclose(out[:, 1], [0.5, 0.02, -0.4, 0.7], atol=1e-6)
  np.testing.assert_array_equal(out[:, 0], np.asarray(wanted)[:, 0])
  with pytest.raises(ValueError, match="max_curvature"):
    policy.actor(CFG, policy.PolicyConfig(max_curvature=-1.0))


def test_safe_speed_stops_the_follower_at_the_minimum_gap():
  """Gipps' safe speed: reacting for `reaction` s and braking at `brake`, the follower stops
  FOLLOW_MIN_GAP behind a leader that brakes as hard; none where the gap is already used up."""
  gap, lead = jnp.array([20.0, 7.0, 40.0, 0.5]), jnp.array([0.0, 10.0, 25.0, 0.0])
  v = np.asarray(policy.safe_speed(gap, lead, 0.5, 4.0))
  room = np.asarray(gap) - policy.FOLLOW_MIN_GAP + np.asarray(lead) ** 2 / 8.0
  np.testing.assert_allclose((v * 0.5 + v ** 2 / 8.0)[:3], room[:3], rtol=1e-5)
  assert v[3] == 0.0


def _follow_scene(speeds, xs, ys, yaws=None, types=None):
  """A make_scene state whose objects are at (xs, ys) at its current step, with headings yaws."""
  from pcdiff_jax.sim.datatypes import ObjectType
  scene = lambda x0: env.reset(make_scene(num_objects=len(speeds), num_steps=91, speeds=speeds, xs=x0, ys=ys))
  elapsed = float(scene(xs).timestep) * CFG.kinematics.dt
  state = scene(tuple(x - v * elapsed for x, v in zip(xs, speeds)))
  cur = state.sim_trajectory
  if yaws is not None:
    yaw = jnp.broadcast_to(jnp.asarray(yaws, jnp.float32)[:, None], cur.yaw.shape)
    speed = jnp.asarray(speeds, jnp.float32)[:, None]
    cur = cur.replace(yaw=yaw, vel_x=speed * jnp.cos(yaw), vel_y=speed * jnp.sin(yaw))
    state = state.replace(sim_trajectory=cur)
  if types is not None:
    state = state.replace(object_metadata=state.object_metadata.replace(
        object_types=jnp.asarray([getattr(ObjectType, t) for t in types], jnp.int32)))
  return state


def test_follow_bound_brakes_behind_the_leader_on_the_planned_path():
  """follow_bound: a car closing on a slow car in its lane gets the hardest braking; a car in the
  next lane, a stopped car beyond where the plan and the stop take the agent, a pedestrian and
  crossing traffic bound nothing; a stopped car across the path does; a queued car may not start
  until its leader does; a leader off the heading line but on a turning plan's path is found."""
  bound = jax.jit(lambda s, p: policy.follow_bound(s, p, (0.5, 4.0), 0.1))
  still = jnp.zeros((4, 80, 2))
  state = _follow_scene((10.0, 2.0, 10.0, 0.0), (0.0, 12.0, 40.0, 60.0), (-2.0, -2.0, 2.0, -2.0))
  np.testing.assert_array_equal(np.asarray(bound(state, still)), [-policy.FOLLOW_MAX_BRAKE] + [np.inf] * 3)
  # The same follower as a pedestrian: no bound.
  walker = _follow_scene((10.0, 2.0, 10.0, 0.0), (0.0, 12.0, 40.0, 60.0), (-2.0, -2.0, 2.0, -2.0),
                         types=("VEHICLE", "PEDESTRIAN", "VEHICLE", "VEHICLE"))
  assert np.asarray(bound(walker, still))[0] == -policy.FOLLOW_MAX_BRAKE
  walker = _follow_scene((10.0, 2.0, 10.0, 0.0), (0.0, 12.0, 40.0, 60.0), (-2.0, -2.0, 2.0, -2.0),
                         types=("PEDESTRIAN", "VEHICLE", "VEHICLE", "VEHICLE"))
  assert np.asarray(bound(walker, still))[0] == np.inf
  # Crossing traffic 15 m ahead: moving, it is the plan's to avoid; standing, it bounds.
  crossing = lambda v: _follow_scene((10.0, v, 0.0, 0.0), (0.0, 15.0, -50.0, -60.0), (-2.0, -2.0, 2.0, 2.0),
                                     yaws=(0.0, np.pi / 2, 0.0, 0.0))
  assert np.asarray(bound(crossing(8.0), still))[0] == np.inf
  assert np.asarray(bound(crossing(0.0), still))[0] < 0.0
  # A queue: stopped 0.8 m behind a stopped leader it stays; it may go once the leader goes.
  queue = lambda v: _follow_scene((0.0, v, 0.0, 0.0), (0.0, 5.3, -50.0, -60.0), (-2.0, -2.0, 2.0, 2.0))
  go = jnp.zeros((4, 80, 2)).at[:, :, 0].set(1.0)
  assert np.asarray(bound(queue(0.0), go))[0] == 0.0
  assert np.asarray(bound(queue(3.0), go))[0] > 1.0
  # A turning plan: the leader 12 m along a left arc of radius 20 m, 3.6 m off the heading line.
  arc = jnp.deg2rad(12.0 / 20.0 * 180.0 / np.pi)
  lead_xy = (20.0 * np.sin(arc), -2.0 + 20.0 * (1.0 - np.cos(arc)))
  turn = _follow_scene((10.0, 0.0, 0.0, 0.0), (0.0, float(lead_xy[0]), -50.0, -60.0),
                       (-2.0, float(lead_xy[1]), 2.0, 2.0), yaws=(0.0, float(arc), 0.0, 0.0))
  left = jnp.zeros((4, 80, 2)).at[0, :, 1].set(10.0 / 20.0)
  assert np.asarray(bound(turn, left))[0] == -policy.FOLLOW_MAX_BRAKE
  assert np.asarray(bound(turn, still))[0] == np.inf


def test_follow_bound_finds_the_car_ahead_of_a_plan_that_stops_short_of_it():
  """A car creeping at 1 m/s 1.2 m (bumper to bumper) behind a standing one, whose plan brakes to
  a stop (or on through zero speed, as a raw plan may) short of it: it is still bounded below
  zero, since the path is searched as far as its front and a leader's centre and ends where the
  plan stops; with no car ahead nothing bounds it. A plan that stopped short had let the rear
  guard's push roll a car into a standing one (docs/RESULTS.md, "Ablation: the follow bound")."""
  bound = jax.jit(lambda s, p: policy.follow_bound(s, p, (0.5, 4.0), 0.1))
  queue = _follow_scene((1.0, 0.0, 0.0, 0.0), (0.0, 5.7, -50.0, -60.0), (-2.0, -2.0, 2.0, 2.0))
  alone = _follow_scene((1.0, 0.0, 0.0, 0.0), (0.0, 40.0, -50.0, -60.0), (-2.0, -2.0, 2.0, 2.0))
  stop = jnp.zeros((4, 80, 2)).at[0, :10, 0].set(-1.0)            # 1 m/s to 0 in 1 s, then holds
  through = jnp.zeros((4, 80, 2)).at[0, :, 0].set(-1.0)           # on to -7 m/s: the path doubles back
  for plan in (stop, through):
    assert float(bound(queue, plan)[0]) < 0.0
    assert float(bound(alone, plan)[0]) == np.inf


def test_follow_bound_sees_a_standing_car_by_its_rotated_box():
  """A car standing 2.6 m beside the path (centre to centre; 4.5 x 2 m boxes) is passed when it
  stands parallel to the path (0.6 m between the boxes) and braked for when it stands at 15
  degrees, its corner within FOLLOW_SIDE_MARGIN of the path: the side-swipes of passing cars on
  real scenes came from leaders the two half widths missed (docs/RESULTS.md, "Ablation: the
  follow bound")."""
  bound = jax.jit(lambda s, p: policy.follow_bound(s, p, (0.5, 4.0), 0.1))
  go = jnp.zeros((4, 80, 2)).at[:, :, 0].set(0.5)
  beside = lambda yaw: _follow_scene((2.0, 0.0, 0.0, 0.0), (0.0, 7.0, -50.0, -60.0), (-2.0, 0.6, 2.0, 2.0),
                                     yaws=(0.0, yaw, 0.0, 0.0))
  assert np.asarray(bound(beside(0.0), go))[0] == np.inf
  assert np.asarray(bound(beside(np.deg2rad(15.0)), go))[0] < 0.0


def test_follow_bound_yields_to_a_slow_crosser_its_plan_would_hit():
  """A car at 5 m/s whose plan keeps its speed and a car creeping north at 1.5 m/s towards its
  lane 8 m ahead: the plan would meet the creeper's side within 2 s, so the first is bounded
  (the creeper, which the first passes in front of, is not: of two that meet, the one that
  would hit the other's side yields, unless the other replays its log); a creeper that has
  cleared the lane before the car arrives bounds nothing, nor does anything with `crossing`
  off."""
  bound = lambda state, **kw: np.asarray(jax.jit(
      lambda s, p: policy.follow_bound(s, p, (0.5, 4.0), 0.1, **kw))(state, jnp.zeros((4, 80, 2))))
  scene = lambda y: _follow_scene((5.0, 1.5, 0.0, 0.0), (0.0, 8.0, -50.0, -60.0), (-2.0, y, 2.0, 2.0),
                                  yaws=(0.0, np.pi / 2, 0.0, 0.0))
  creeping = bound(scene(-6.0))
  assert creeping[0] < 0.0 and creeping[1] == np.inf
  assert bound(scene(-6.0), crossing=False)[0] == np.inf
  assert bound(scene(2.5))[0] == np.inf   # its side beyond the lane's far edge already
  # The first car on its log (not a follower): the creeper yields to it, since it will not yield.
  creeper_only = bound(scene(-6.0), followers=jnp.asarray([False, True, False, False]), max_followers=4)
  assert creeper_only[1] < np.inf and creeper_only[0] == np.inf


def test_crossing_objects_are_ranked_by_how_near_they_come_to_the_plan():
  """crossing_gaps checks each follower's `nearest` moving objects by how close they come to its
  plan within 2 s, not by where they are now: a car 7 m away driving off is passed over for a
  fast crosser 23 m away that the plan would meet, and one object searched finds it."""
  from pcdiff_jax.policy import execution
  from pcdiff_jax.sim import dynamics
  state = _follow_scene((10.0, 12.0, 10.0), (0.0, 17.0, -5.0), (0.0, -18.0, 5.0),
                        yaws=(0.0, np.pi / 2, np.pi))
  cur = state.current_sim_trajectory
  states = dynamics.rollout(dynamics.states_from_trajectory(cur)[:1, 0], jnp.zeros((1, 80, 2)), 0.1)
  gaps = lambda n: np.asarray(execution.crossing_gaps(states, jnp.asarray([0]), cur, jnp.ones(3, bool),
                                                      jnp.ones(3, bool), 0.1, nearest=n))
  every, one = gaps(3), gaps(1)                                       # (1, N): the searched objects
  assert np.isfinite(every).sum() == 1                                # the crosser bounds, the other car not
  assert one.shape == (1, 1) and one[0, 0] == every.min()


def test_rear_guard_speeds_up_before_an_object_on_its_log_closing_from_behind():
  """rear_guard: a car at 5 m/s with a car on its log (not a follower) 10 m behind at 12 m/s
  gets at least the acceleration that matches that speed before the gap closes, capped at
  REAR_GUARD_MAX_ACCEL, passed on to a car of ours close ahead of it; nothing where the closing
  car reacts (a follower), drives out of line (the next lane; a parked car its centre passes
  beside), is ahead or more than 4 s away, nor for it. In `execute` the follow bound still wins
  over it."""
  from pcdiff_jax.policy import execution
  state = _follow_scene((5.0, 12.0, 12.0, 0.0), (0.0, -10.0, -10.0, 60.0), (-2.0, -2.0, 2.0, -2.0))
  mask = lambda *on: jnp.asarray(on)
  guard = np.asarray(execution.rear_guard(state, mask(True, False, True, True)))
  assert guard[0] == execution.REAR_GUARD_MAX_ACCEL and np.all(guard[1:] == -np.inf)
  assert np.all(np.asarray(execution.rear_guard(state, mask(True, True, True, True))) == -np.inf)
  slow = _follow_scene((5.0, 9.0, 0.0, 0.0), (0.0, -10.0, 40.0, 60.0), (-2.0, -2.0, 2.0, -2.0))
  need = np.asarray(execution.rear_guard(slow, mask(True, False, True, True)))[0]
  gap = 10.0 - 0.5 * float(slow.current_sim_trajectory.length[0, 0] + slow.current_sim_trajectory.length[1, 0])
  np.testing.assert_allclose(need, 4.0 ** 2 / (2.0 * (gap - execution.FOLLOW_MIN_GAP)), rtol=1e-4)
  far = _follow_scene((5.0, 6.0, 0.0, 0.0), (0.0, -40.0, 40.0, 60.0), (-2.0, -2.0, 2.0, -2.0))
  assert np.asarray(execution.rear_guard(far, mask(True, False, True, True)))[0] == -np.inf   # 35 s away
  # A queue of ours: the push passes to the car 3 m ahead of the pushed one, not to one 20 m ahead.
  queue = lambda lead_x: _follow_scene((5.0, 5.0, 12.0, 0.0), (lead_x, 0.0, -10.0, 60.0), (-2.0, -2.0, -2.0, 2.0))
  near = np.asarray(execution.rear_guard(queue(7.5), mask(True, True, False, True)))
  assert near[1] > 0.0 and near[0] == near[1]
  far = np.asarray(execution.rear_guard(queue(24.5), mask(True, True, False, True)))
  assert far[1] == near[1] and far[0] == -np.inf
  # 1.2 m to the side of the closing car's line, a car at 2 m/s is pushed (the 2 m wide boxes meet
  # sideways); a parked one is not (drivers steer round it), nor one 2.5 m to the side.
  beside = lambda v, y: np.asarray(execution.rear_guard(_follow_scene(
      (v, 9.0, 0.0, 0.0), (0.0, -10.0, 40.0, 60.0), (-2.0, y, 2.0, -2.0)), mask(True, False, True, True)))[0]
  assert beside(2.0, -0.8) > 0.0 and beside(2.0, 0.5) == -np.inf
  assert beside(0.0, -0.8) == -np.inf and beside(0.0, -2.0) > 0.0
  # A stopped leader 12 m ahead: the follow bound's limit, below the guard's acceleration.
  boxed = _follow_scene((5.0, 12.0, 0.0, 0.0), (0.0, -10.0, 12.0, 60.0), (-2.0, -2.0, -2.0, 2.0))
  on = policy.PolicyConfig(rear_guard=True)
  now, _ = policy.execute(boxed, jnp.zeros((4, 80, 2)), jnp.zeros((4, 80, 2)), 0, on, CFG, jnp.zeros(4),
                          followers=mask(True, False, True, True))
  limit = policy.follow_bound(boxed, jnp.zeros((4, 80, 2)), on.follow, 0.1, mask(True, False, True, True),
                              CFG.features.max_agents)
  assert float(now[0, 0]) == float(limit[0]) < execution.REAR_GUARD_MAX_ACCEL
  now, _ = policy.execute(state, jnp.zeros((4, 80, 2)), jnp.zeros((4, 80, 2)), 0, on, CFG, jnp.zeros(4),
                          followers=mask(True, False, True, True))
  assert float(now[0, 0]) == execution.REAR_GUARD_MAX_ACCEL


def test_follow_bound_searches_leaders_for_the_followers_only():
  """follow_bound with a followers mask (the executed agents): the same bound for each follower
  as over every object, leaders found among all objects, +inf for the others."""
  state = _follow_scene((10.0, 2.0, 10.0, 0.0), (0.0, 12.0, 40.0, 60.0), (-2.0, -2.0, 2.0, -2.0))
  still = jnp.zeros((4, 80, 2))
  every = np.asarray(jax.jit(lambda s, p: policy.follow_bound(s, p, (0.5, 4.0), 0.1))(state, still))
  some = jnp.asarray([True, False, True, False])
  chosen = np.asarray(jax.jit(lambda s, p: policy.follow_bound(s, p, (0.5, 4.0), 0.1, some, 3))(state, still))
  np.testing.assert_array_equal(chosen, [every[0], np.inf, every[2], np.inf])
  assert chosen[0] == -policy.FOLLOW_MAX_BRAKE


def test_follow_is_applied_after_the_jerk_limit():
  """execute with `follow` on: the bound overrides the plan and the jerk limit (a safety bound,
  not comfort), and off it changes nothing."""
  state = _follow_scene((10.0, 2.0, 10.0, 0.0), (0.0, 12.0, 40.0, 60.0), (-2.0, -2.0, 2.0, -2.0))
  plan = jnp.zeros((4, 80, 2)).at[:, :, 0].set(1.0)
  path = jnp.zeros((4, 80, 2))
  on = policy.PolicyConfig(follow=(0.5, 4.0))
  now, reference = policy.execute(state, plan, path, 0, on, CFG, jnp.zeros(4))
  np.testing.assert_allclose(np.asarray(now)[:, 0], [-policy.FOLLOW_MAX_BRAKE, 0.15, 0.15, 0.15], atol=1e-6)
  # The jerk limit's next reference is the acceleration before the bound: the forced braking
  # does not linger once the leader is gone.
  np.testing.assert_allclose(np.asarray(reference), 0.15, atol=1e-6)
  off, _ = policy.execute(state, plan, path, 0, dataclasses.replace(on, follow=(0.0, 0.0)), CFG, jnp.zeros(4))
  np.testing.assert_allclose(np.asarray(off)[:, 0], 0.15, atol=1e-6)
  with pytest.raises(ValueError, match="follow"):
    policy.actor(CFG, policy.PolicyConfig(follow=(0.5, 0.0)))


def test_policy_fields_are_set_by_name_with_their_types():
  """with_overrides (`experiments.rollout --policy FIELD=VALUE`) converts strings to each field's
  type, tuples element-wise, and names the fields when one is unknown."""
  cfg = policy.with_overrides(policy.PolicyConfig(), [("max_curvature", "0.3"), ("still_gate", ("2", "1.5")),
                                                       ("stop_hold", "false"), ("select_samples", "4")])
  assert cfg.max_curvature == 0.3 and cfg.still_gate == (2.0, 1.5) and cfg.stop_hold is False
  assert cfg.select_samples == 4
  with pytest.raises(ValueError, match="unknown policy field 'speed'.*max_curvature"):
    policy.with_overrides(policy.PolicyConfig(), [("speed", "1")])


def test_still_gate_keeps_agents_the_proposals_keep_still(models):
  """still_gate: an agent slower than START_GATE_SPEED whose proposals (probability-weighted)
  travel less than `metres` within `seconds` gets a plan that stops it and holds it: in closed
  loop it stays exactly where it is, heading included; a gate nothing passes under (0 m) changes
  nothing, and a fast agent is never held."""
  from pcdiff_jax.sim import dynamics
  scene = make_scene(num_steps=91, speeds=(10.0, 0.0, 0.3, 8.0))
  base = policy.PolicyConfig(ddim_steps=2, select_samples=1, warm_start=False, temporal_ensemble=(0.0, 0.0),
                             still_gate=(0.0, 0.0))
  held_cfg = dataclasses.replace(base, still_gate=(2.0, 1e3))
  free_cfg = dataclasses.replace(base, still_gate=(2.0, 0.0))
  state = env.reset(scene)
  rng = jax.random.key(3)
  plan = lambda c: np.asarray(jax.jit(lambda s, r: policy.plan_actions(models, s, CFG, c, r)[0])(state, rng))
  free = plan(base)
  np.testing.assert_allclose(plan(free_cfg), free, atol=1e-5)   # separate programs: float order only
  held = plan(held_cfg)
  np.testing.assert_allclose(held[1], 0.0, atol=1e-6)                       # stopped: nothing to do
  np.testing.assert_allclose(held[2, 0], [-3.0, 0.0], atol=1e-5)            # 0.3 m/s: one braking step
  np.testing.assert_allclose(held[2, 1:], 0.0, atol=1e-6)
  np.testing.assert_allclose(held[3], free[3], atol=1e-5)                    # 8 m/s: never held
  act = policy.actor(CFG, held_cfg)
  select = jax.jit(act.select_action)
  start = np.asarray(state.current_sim_trajectory.xy)[1, 0], np.asarray(state.current_sim_trajectory.yaw)[1, 0]
  ps = act.init(jax.random.key(0), state)
  for k in range(6):   # the 0.3 m/s agent, jerk-limited, stops within 5 steps at 5 Hz (3 at 10 Hz)
    out = select(models, state, ps, jax.random.key(k))
    ps = out.actor_state
    state = env.step(state, out.action, out.is_controlled)
  np.testing.assert_allclose(np.asarray(state.current_sim_trajectory.xy)[1, 0], start[0], atol=1e-5)
  np.testing.assert_allclose(np.asarray(state.current_sim_trajectory.yaw)[1, 0], start[1], atol=1e-6)
  speed = np.asarray(dynamics.states_from_trajectory(state.current_sim_trajectory))[1:3, 0, dynamics.V]
  np.testing.assert_allclose(speed, 0.0, atol=1e-5)
  with pytest.raises(ValueError, match="still_gate"):
    policy.actor(CFG, policy.PolicyConfig(still_gate=(2.0, -1.0)))


def test_a_noisy_logged_speed_does_not_force_an_acceleration(models):
  """A logged speed jump at the rollout's start (real logs' noisy speeds and headings read as
  tens of m/s^2) must not become the jerk limit's reference: the first step is limited around
  the log's trend over a second (`logged_accel`, bounded), the next ones around what the policy
  executed."""
  state = env.reset(make_scene(num_steps=91))
  log = state.log_trajectory
  t = int(state.timestep)
  jump = log.replace(vel_x=log.vel_x.at[:, t - 1].multiply(0.2))     # the step before: 5x slower
  noisy = state.replace(log_trajectory=jump, sim_trajectory=jump)
  dt = CFG.kinematics.dt
  assert float(jnp.max(jnp.abs(policy.executed_accel(noisy, dt)))) > 20.0
  trend = np.asarray(policy.logged_accel(noisy, dt))
  np.testing.assert_allclose(trend, 0.0, atol=1e-4)                  # constant speeds over the second
  ramp = noisy.sim_trajectory.replace(vel_x=noisy.sim_trajectory.vel_x.at[:, t - 10].add(-30.0))
  ramped = np.abs(np.asarray(policy.logged_accel(noisy.replace(sim_trajectory=ramp), dt)))
  bound = policy.PolicyConfig().jerk_start_bound
  assert np.all(ramped <= bound + 1e-6) and ramped.max() == pytest.approx(bound)
  tight = policy.actor(CFG, policy.PolicyConfig(select_samples=1, jerk_start_bound=0.5))
  start = jax.jit(tight.init)(jax.random.PRNGKey(0), noisy.replace(sim_trajectory=ramp))
  assert np.abs(np.asarray(start.accel)).max() == pytest.approx(0.5)      # the actor reads its bound
  act = policy.actor(CFG, policy.PolicyConfig(select_samples=1, jerk_limit=(1.5, 5.0), still_gate=(0.0, 0.0)))
  ps = jax.jit(act.init)(jax.random.PRNGKey(0), noisy)
  np.testing.assert_allclose(np.asarray(ps.accel), trend)
  out = jax.jit(act.select_action)(models, noisy, ps, jax.random.PRNGKey(1))   # one program, not op by op
  controlled = np.asarray(out.is_controlled)
  first = np.asarray(out.action.data)[controlled, 0]
  moving = np.asarray(dynamics.states_from_trajectory(noisy.current_sim_trajectory))[controlled, 0, 3] > 0.5
  assert np.all(first[moving] <= 1.5 * dt + 1e-5) and np.all(first[moving] >= -5.0 * dt - 1e-5), first
  np.testing.assert_allclose(np.asarray(out.actor_state.accel)[controlled], first, atol=1e-6)
  # The stateless step reads the state's one-step estimate, bounded by the model's limit.
  action, _ = jax.jit(lambda s, r: policy.step(s, models, CFG, r, policy.PolicyConfig(
      select_samples=1, still_gate=(0.0, 0.0))))(noisy, jax.random.PRNGKey(1))
  assert np.all(np.abs(np.asarray(action.data)[:, 0]) <= CFG.kinematics.max_accel + 1e-5)



def test_cruise_floor_holds_a_fast_car_on_a_free_straight_road():
  """cruise_floor: a car at 20 m/s with nothing ahead on its straight plan may brake at most
  hold[1]; nothing is held behind a slow car in its lane (the follow bound would brake), on a
  plan that turns, below hold[0], nor for a pedestrian. In `execute` a plan braking at 4 m/s^2
  is held there, and the follow bound still wins behind a leader."""
  from pcdiff_jax.policy import execution
  hold = (15.0, 1.0)
  floor = lambda s, p: np.asarray(execution.cruise_floor(
      s, p, policy.follow_bound(s, p, (0.5, 4.0), 0.1), hold))
  straight = jnp.zeros((4, 80, 2))
  free = _follow_scene((20.0, 5.0, 20.0, 10.0), (0.0, 15.0, -200.0, 300.0), (-2.0, 2.0, 6.0, -2.0))
  np.testing.assert_array_equal(floor(free, straight), [-1.0, -np.inf, -1.0, -np.inf])
  led = _follow_scene((20.0, 5.0, 20.0, 10.0), (0.0, 15.0, -200.0, 300.0), (-2.0, -2.0, 6.0, -2.0))
  assert floor(led, straight)[0] == -np.inf
  turning = straight.at[:, :, 1].set(0.2)          # 4 m/s^2 of lateral acceleration at 20 m/s
  assert floor(free, turning)[0] == -np.inf
  walker = _follow_scene((20.0, 5.0, 20.0, 10.0), (0.0, 15.0, -200.0, 300.0), (-2.0, 2.0, 6.0, -2.0),
                         types=("PEDESTRIAN", "VEHICLE", "VEHICLE", "VEHICLE"))
  assert floor(walker, straight)[0] == -np.inf
  on = policy.PolicyConfig(cruise_hold=hold, jerk_limit=(0.0, 0.0))
  braking = straight.at[:, :, 0].set(-4.0)
  now, _ = policy.execute(free, braking, jnp.zeros((4, 80, 2)), 0, on, CFG, jnp.zeros(4))
  assert float(now[0, 0]) == -1.0 and float(now[3, 0]) == -4.0
  now, _ = policy.execute(led, braking, jnp.zeros((4, 80, 2)), 0, on, CFG, jnp.zeros(4))
  assert float(now[0, 0]) <= -4.0
  with pytest.raises(ValueError, match="cruise_hold"):
    policy.actor(CFG, policy.PolicyConfig(cruise_hold=(15.0, -1.0)))


def test_map_spare_allows_what_a_likely_proposal_leaving_the_road_costs(models):
  """proposal_map_allowance: object 2 of make_scene stands 2.5 m off the road, so each of its
  proposals takes a corner past the edge and its allowance is its likeliest such J_map > 0;
  no proposal is that likely (probability > 1) or leaves the road 1 km: no allowance. The
  sample selection runs with the spare; the policy refuses a bad one."""
  from pcdiff_jax.model import guidance as guidance_lib
  from pcdiff_jax.policy import planning, selection
  from pcdiff_jax.sim.datatypes import ObjectType
  state = env.reset(make_scene(num_steps=91))
  pcfg = policy.PolicyConfig(select_samples=2)

  @jax.jit
  def run(state):
    scene = planning.encode(models, state, CFG, pcfg)
    road = planning.road_for(state, pcfg).in_frame(scene.feats.scene_xy, scene.feats.scene_yaw)
    road = jax.tree_util.tree_map(lambda a: a[None], road)
    length, width = planner.agent_size(scene.feats)
    agents = guidance_lib.Agents(length=length, width=width, valid=scene.feats.agent_valid,
                                 vehicle=scene.feats.agent_types == ObjectType.VEHICLE,
                                 pursuer=jnp.int32(-1), evader=jnp.int32(-1))
    allow = lambda p, m: selection.proposal_map_allowance(
        models, scene.cond, scene.feats, CFG, pcfg.select_lookahead, pcfg.select_stride, agents,
        road, pcfg.guidance, p, m)
    noise = 3.0 * jax.random.normal(jax.random.key(1), scene.cond.mu[0].shape)
    y0 = jnp.stack([scene.cond.mu[0], scene.cond.mu[0] + noise])          # (2, A, d)
    chosen = selection.select_sample(
        y0, models, scene.cond, scene.batched, CFG, pcfg.select_lookahead,
        jnp.arange(y0.shape[1]) == 0, road, pcfg.select_map_weight, pcfg.guidance,
        pcfg.select_stride, map_spare=(0.0, 1.0))
    return (scene.feats.agent_index, allow(0.0, 1.0), allow(1.01, 0.0), allow(0.0, 1000.0), chosen)

  index, spared, unlikely, far, chosen = map(np.asarray, run(state))
  assert spared[int(np.argmax(index == 2))] > 0
  assert (spared >= 0).all() and np.isfinite(spared).all() and np.isfinite(chosen).all()
  assert not unlikely.any() and not far.any()
  with pytest.raises(ValueError, match="select_map_spare"):
    policy.actor(CFG, policy.PolicyConfig(select_map_spare=(1.5, 1.0)))


def test_pedestrians_plan_on_their_proposals(models):
  """pedestrian_plan: object 3 of make_scene made a pedestrian gets its likeliest proposal
  ("top") in every sample, or ("drawn") on a warm replan the proposal nearest its previous plan
  in sample 0 and proposals in the others, ("mixed") so in the first half of the samples and the
  denoiser's in the rest, ("steady") as "mixed" with its speed and heading held in sample 0 if it
  walks; the vehicles' samples are the denoiser's either way, the same draws as "sample"; a
  guided plan keeps the pedestrian's guided sample."""
  from pcdiff_jax.policy import planning
  from pcdiff_jax.sim.datatypes import ObjectType
  state = env.reset(make_scene(num_steps=91))
  md = state.object_metadata
  state = state.replace(object_metadata=md.replace(
      object_types=md.object_types.at[3].set(ObjectType.PEDESTRIAN)))
  pcfg = policy.PolicyConfig(select_samples=3)
  road = planning.road_for(state, pcfg)
  rng = jax.random.key(0)

  @functools.partial(jax.jit, static_argnums=(0, 2))
  def draw(how, warm, guidance=None):
    p = dataclasses.replace(pcfg, pedestrian_plan=how)
    if guidance is not None:
      p = dataclasses.replace(p, guidance=guidance)
    scene = planning.encode(models, state, CFG, p)
    return scene, planning.sample(models, scene, CFG, p, rng, -1, road, warm=warm)

  scene, sampled = draw("sample", None)
  _, top = draw("top", None)
  slot = int(np.argmax(np.asarray(scene.feats.agent_index) == 3))
  props, probs = np.asarray(scene.cond.proposals[0, slot]), np.asarray(scene.cond.probs[0, slot])
  walker = np.arange(sampled.shape[1]) == slot
  np.testing.assert_allclose(np.asarray(top)[:, slot], np.broadcast_to(props[np.argmax(probs)], (3, props.shape[-1])))
  np.testing.assert_array_equal(np.asarray(top)[:, ~walker], np.asarray(sampled)[:, ~walker])
  # A warm replan whose previous plan for the pedestrian is its least likely proposal keeps it.
  least = int(np.argmin(probs))
  from pcdiff_jax.model import latent
  plan = latent.decode(jnp.asarray(props[least]), models.stats)                     # (T, 2)
  actions = jnp.zeros((4,) + plan.shape).at[3].set(plan)
  warm = planning.WarmStart(actions=actions, has=jnp.arange(4) == 3)
  _, drawn = draw("drawn", warm)
  drawn = np.asarray(drawn)[:, slot]
  np.testing.assert_allclose(drawn[0], props[least], atol=1e-5)
  assert all(np.abs(props - y).max(-1).min() < 1e-5 for y in drawn[1:])   # each another proposal
  # "mixed": the first half of the samples as "drawn" (here sample 0), the rest the denoiser's.
  _, mixed = draw("mixed", warm)
  _, warm_sampled = draw("sample", warm)
  np.testing.assert_allclose(np.asarray(mixed)[0, slot], props[least], atol=1e-5)
  np.testing.assert_array_equal(np.asarray(mixed)[1:, slot], np.asarray(warm_sampled)[1:, slot])
  np.testing.assert_array_equal(np.asarray(mixed)[:, ~walker], np.asarray(warm_sampled)[:, ~walker])
  # "steady": sample 0 holds the pedestrian's speed and heading (zero actions) where its
  # tracked speed is within 0.5 m/s of its last second's, else its mode (a jittery track); the
  # rest as "mixed".
  recent = float(planning.recent_speed(scene.feats, CFG.kinematics.dt)[slot])
  zero = np.asarray(latent.encode(jnp.zeros((models.stats.horizon, 2)), models.stats))
  for speed, expected in ((recent + 0.2, zero), (recent + 2.0, props[np.argmax(probs)])):
    cond = scene.cond.replace(speed=scene.cond.speed.at[:, slot].set(speed))
    steady = planning.on_proposals(warm_sampled, cond, scene.feats, "steady", rng,
                                   stats=models.stats, kinematics=CFG.kinematics)
    np.testing.assert_allclose(np.asarray(steady)[0, slot], expected, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(steady)[1:], np.asarray(warm_sampled)[1:])
    np.testing.assert_array_equal(np.asarray(steady)[:, ~walker], np.asarray(warm_sampled)[:, ~walker])
  # A guided plan keeps every agent's guided sample: a proposal would bypass the guidance.
  from pcdiff_jax.model.guidance import GuidanceConfig
  objective = GuidanceConfig(mode="objective")
  np.testing.assert_array_equal(np.asarray(draw("mixed", None, objective)[1]),
                                np.asarray(draw("sample", None, objective)[1]))
  with pytest.raises(ValueError, match="pedestrian_plan"):
    policy.actor(CFG, policy.PolicyConfig(pedestrian_plan="walk"))
  # cyclist_plan: the same plans for the cyclists alone (kind), none for the pedestrian.
  types = scene.feats.agent_types
  ridden = planning.on_proposals(sampled, scene.cond, scene.feats, "top", rng, kind=ObjectType.CYCLIST)
  np.testing.assert_array_equal(np.asarray(ridden), np.asarray(sampled))
  rider = scene.feats.replace(agent_types=types.at[slot].set(ObjectType.CYCLIST))
  ridden = planning.on_proposals(sampled, scene.cond, rider, "top", rng, kind=ObjectType.CYCLIST)
  np.testing.assert_array_equal(np.asarray(ridden), np.asarray(top))
  with pytest.raises(ValueError, match="cyclist_plan"):
    policy.actor(CFG, policy.PolicyConfig(cyclist_plan="ride"))


def test_recent_speed():
  """recent_speed: the mean speed over the last second of valid history positions (agent
  frame, the current step at the origin); a track younger than that spans what it has, one
  with no earlier step has 0."""
  import types
  from pcdiff_jax.policy import planning
  steps = np.arange(11)
  hist = np.zeros((3, 11, 4), np.float32)
  hist[0, :, 0] = -1.2 * (10 - steps) * 0.1        # 1.2 m/s for 1 s
  hist[1, :, 1] = 0.5 * (10 - steps) * 0.1         # 0.5 m/s sideways, valid for 0.3 s
  valid = np.ones((3, 11), bool)
  valid[1, :7] = False
  valid[2, :10] = False                              # only the current step
  feats = types.SimpleNamespace(agent_history=jnp.asarray(hist), agent_history_valid=jnp.asarray(valid))
  np.testing.assert_allclose(np.asarray(planning.recent_speed(feats, 0.1)), [1.2, 0.5, 0.0], atol=1e-5)


def test_holds_pace(models):
  """holds_pace: a steady plan suits a walker whose tracked speed is its last second's, not a
  jittery track; with min_travel, not one whose mode stops (at a kerb) either."""
  import types
  from pcdiff_jax.model import latent
  from pcdiff_jax.policy import planning
  steps = np.arange(11)
  hist = np.zeros((3, 11, 4), np.float32)
  hist[:, :, 0] = -1.2 * (10 - steps) * 0.1                                   # 1.2 m/s for 1 s
  feats = types.SimpleNamespace(agent_history=jnp.asarray(hist), agent_history_valid=jnp.ones((3, 11), bool))
  horizon = models.stats.horizon
  walk = jnp.zeros((horizon, 2))
  stop = walk.at[:10, 0].set(-1.2)                                              # stops within 1 s
  mode = latent.encode(jnp.stack([walk, stop, walk]), models.stats)           # (3, d)
  speed = jnp.asarray([1.2, 1.2, 3.5])                                          # the last: jittery
  holds = lambda travel: np.asarray(planning.holds_pace(mode, speed, feats, models.stats, CFG.kinematics, travel))
  np.testing.assert_array_equal(holds(0.5), [True, False, False])
  np.testing.assert_array_equal(holds(0.0), [True, True, False])   # the default: the speed check only
