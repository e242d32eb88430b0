"""Training: losses and metrics, batches, example targets, the train CLI on bad input
(the CLI on a trained model: test_trained_pipeline.py)."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax.config import get_config
from pcdiff_jax.model import denoiser as denoiser_lib
from pcdiff_jax.model import planner
from pcdiff_jax.model.encoder import EncoderOutput
from pcdiff_jax.training import data as data_lib
from pcdiff_jax.training import encoder_loss

CFG = get_config("tiny")


def _output(traj, logits, valid):
  a, k = logits.shape
  z = jnp.zeros((a, 4))
  return EncoderOutput(agent_tokens=z, agent_valid=valid, map_tokens=z, map_valid=valid,
                       trajectories=traj, yaws=traj[..., 0] * 0, control_points=traj[..., :2, :],
                       logits=logits, probs=jax.nn.softmax(logits))


def test_wta_loss_and_metrics_on_a_known_case():
  """Agent 0: mode 1 is exact. Agent 1: padded (ignored even with garbage)."""
  T = 80
  s = jnp.arange(1, T + 1) * 0.1
  target = jnp.stack([10.0 * s, 0 * s], -1)                           # 10 m/s straight
  traj = jnp.stack([target + 3.0, target, target - 5.0])[None]       # (1, K=3, T, 2)
  traj = jnp.concatenate([traj, jnp.full((1, 3, T, 2), 1e3)])
  logits = jnp.array([[0.0, 5.0, 0.0], [0.0, 0.0, 0.0]])
  out = _output(traj, logits, jnp.array([True, False]))
  hist = jnp.zeros((2, 11, 14)).at[:, -1, 6].set(10.0)               # vel_x = 10 m/s at t
  from pcdiff_jax.model.features import SceneFeatures
  feats = SceneFeatures(**{f: None for f in SceneFeatures.__dataclass_fields__}).replace(
      agent_history=hist)
  targets = data_lib.Targets(future_xy=jnp.stack([target, target]), future_yaw=jnp.zeros((2, T)),
                             future_speed=jnp.full((2, T), 10.0), future_valid=jnp.ones((2, T), bool),
                             current_speed=jnp.full((2,), 10.0))
  loss, parts = encoder_loss.proposal_loss(out, targets)
  assert float(parts["reg"]) == pytest.approx(0.0, abs=1e-5)
  ce = -float(jax.nn.log_softmax(logits[0])[1])
  assert float(parts["cls"]) == pytest.approx(ce, rel=1e-5)
  m = encoder_loss.finalize(jax.device_get(encoder_loss.prediction_metrics(out, feats, targets)))
  assert m["count"] == 1 and m["min_ade"] == pytest.approx(0, abs=1e-4)
  assert m["min_fde"] == pytest.approx(0, abs=1e-4) and m["miss_rate"] == 0
  assert m["brier_min_fde"] == pytest.approx((1 - float(out.probs[0, 1])) ** 2, rel=1e-4)
  assert m["cv_fde"] == pytest.approx(0, abs=1e-3)                    # CV is exact here
  # Gradients of the loss are finite despite the padded agent's garbage.
  g = jax.grad(lambda tr: encoder_loss.proposal_loss(_output(tr, logits, out.agent_valid), targets)[0])(traj)
  assert np.all(np.isfinite(np.asarray(g))) and float(jnp.abs(g[1]).max()) == 0


def test_batches_are_a_pure_function_of_the_step():
  ex = data_lib.Example(feats=np.arange(10), targets=np.arange(10) * 2)
  ex = jax.tree_util.tree_map(np.asarray, ex)
  pick = lambda step: data_lib.batch_at(ex, step, 3, seed=4).feats.tolist()
  assert pick(7) == pick(7)
  epoch0 = sum((pick(i) for i in range(3)), [])
  assert len(set(epoch0)) == 9                                       # no repeats within an epoch


@pytest.fixture(scope="module")
def scene_example():
  """make_scene (4 agents driving, 91 steps) as a batch of one Example at t = 10."""
  state = make_scene(num_steps=91)
  fn = jax.jit(lambda s: data_lib.example_at(s, 10, CFG.features, CFG.encoder.horizon))
  ex = fn(state)
  return jax.tree_util.tree_map(lambda a: a[None], ex)


def test_targets_are_the_logged_future_in_the_agent_frame(scene_example):
  t = scene_example.targets
  # Agent 0 (the SDC) drives at 10 m/s along x: its future is (1 m per step, 0).
  np.testing.assert_allclose(np.asarray(t.future_xy[0, 0, :5, 0]), [1, 2, 3, 4, 5], atol=1e-4)
  assert bool(t.future_valid[0, 0].all()) and float(t.current_speed[0, 0]) == pytest.approx(10.0)
  assert not bool(t.future_valid[0, 4:].any())                      # padded slots


def test_agents_whose_log_overlaps_another_box_can_be_left_out_of_training():
  """Object 0 drives at 10 m/s into object 2, which stands 60 m ahead in its lane (their boxes
  overlap from about 5.6 s): with drop_log_overlaps both get no valid target step at t = 10,
  the others keep theirs; without it nothing changes; a horizon that ends before the overlap
  drops nobody."""
  state = make_scene(num_steps=91, xs=(0.0, 0.0, 60.0, -30.0), ys=(-2.0, 2.0, -2.0, -2.0))
  at10 = state.replace(sim_trajectory=state.log_trajectory, timestep=jnp.asarray(10, jnp.int32))
  idx = jnp.arange(4)
  # Jitted: op by op, every op compiles on its own (2x the test's time on 2 cores).
  ahead = jax.jit(data_lib.log_overlaps_ahead, static_argnums=2)
  assert ahead(at10, idx, 80).tolist() == [True, False, True, False]
  assert not ahead(at10, idx, 30).any()
  example = lambda drop: jax.jit(lambda s: data_lib.example_at(s, 10, CFG.features, 80,
                                                               drop_log_overlaps=drop))(state)
  kept, dropped = example(False), example(True)
  trained = lambda ex: {int(o): bool(v.any()) for o, v, ok in zip(
      ex.feats.agent_index, ex.targets.future_valid, ex.feats.agent_valid) if ok}
  assert trained(kept) == {0: True, 1: True, 2: True, 3: True}
  assert trained(dropped) == {0: False, 1: True, 2: False, 3: True}
  assert data_lib.cache_key([], data_lib.CacheSpec(CFG.features)) != data_lib.cache_key(
      [], data_lib.CacheSpec(CFG.features, drop_log_overlaps=True))


def test_vehicles_whose_log_leaves_the_road_can_be_left_out_of_training():
  """Object 1's log drifts left from y = 1.5 m at t = 10 across the road edge at y = 4 (its box
  corner from about step 40): with drop_log_offroad it gets no valid target step, the others
  keep theirs, object 2 too (off the road from the start: parked, not leaving); a pedestrian
  that does the same stays in, and a horizon that ends before the edge drops nobody."""
  state = make_scene(num_steps=91)
  log = state.log_trajectory
  drift = log.y.at[1].set(1.0 + 0.05 * jnp.arange(91, dtype=jnp.float32))
  state = state.replace(log_trajectory=log.replace(y=drift), sim_trajectory=log.replace(y=drift))
  at10 = state.replace(sim_trajectory=state.log_trajectory, timestep=jnp.asarray(10, jnp.int32))
  idx = jnp.arange(4)
  leaves = jax.jit(data_lib.log_leaves_road_ahead, static_argnums=2)
  assert leaves(at10, idx, 80).tolist() == [False, True, False, False]
  assert not leaves(at10, idx, 20).any()
  md = at10.object_metadata
  walker = at10.replace(object_metadata=md.replace(object_types=md.object_types.at[1].set(2)))
  assert not leaves(walker, idx, 80).any()
  ex = jax.jit(lambda s: data_lib.example_at(s, 10, CFG.features, 80, drop_log_offroad=True))(state)
  trained = {int(o): bool(v.any()) for o, v, ok in zip(ex.feats.agent_index, ex.targets.future_valid,
                                                       ex.feats.agent_valid) if ok}
  assert trained == {0: True, 1: False, 2: True, 3: True}
  assert data_lib.cache_key([], data_lib.CacheSpec(CFG.features)) != data_lib.cache_key(
      [], data_lib.CacheSpec(CFG.features, drop_log_offroad=True))


def test_diffusion_loss_finite_with_masked_agents(scene_example):
  from pcdiff_jax.model import encoder, latent
  from pcdiff_jax.training import diffusion_stage
  enc = encoder.init(jax.random.key(0), scene_example.feats, CFG.encoder)
  stats = diffusion_stage.fit_latent(enc, CFG, scene_example, 1, batch_size=1)
  cond = jax.jit(lambda f: planner.condition(enc, stats, f, CFG))(scene_example.feats)
  one = jax.tree_util.tree_map(lambda a: a[0], cond.inputs)
  params = denoiser_lib.init(jax.random.key(1), cond.mu[0], jnp.int32(0), one, CFG.diffusion.denoiser)
  extra = {"encoder": enc, "stats": stats}
  # Agent 1 loses its last future step (not scored); agent 2 is dropped entirely.
  tg = scene_example.targets
  tg = tg.replace(future_valid=tg.future_valid.at[0, 1, -1].set(False))
  feats = scene_example.feats.replace(agent_valid=scene_example.feats.agent_valid.at[0, 2].set(False))
  batch = scene_example.replace(targets=tg, feats=feats)
  loss_fn = lambda p: diffusion_stage.diffusion_loss(p, extra, batch, jax.random.key(2), CFG)[0]
  loss, grads = jax.jit(jax.value_and_grad(loss_fn))(params)
  assert np.isfinite(float(loss))
  assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree_util.tree_leaves(grads))
  # The denoiser is zero on padded agents and joint: agent 0's output depends on agent 1's input.
  y = jax.random.normal(jax.random.key(3), cond.mu.shape)
  dc, dim = CFG.diffusion.denoiser, y.shape[-1]
  # Jitted: the same ops run eagerly compile one by one (most of this test's time on CPU).
  apply = jax.jit(lambda y, inputs: denoiser_lib.apply(params, y, jnp.int32(50), inputs, dc))
  out = apply(y, cond.inputs)
  assert float(jnp.abs(out[0, 5:]).max()) == 0.0
  # The y-independent context, computed once per chain (planner.sample), gives the same
  # output, per scene or shared by several samples of one scene (sample selection).
  ys = jnp.concatenate([y, 2.0 * y, -y])
  with_context = jax.jit(lambda y, ys: [denoiser_lib.apply_with_context(
      params, v, jnp.int32(50), denoiser_lib.context(params, cond.inputs, dc, dim), dc) for v in (y, ys)])
  one, shared = with_context(y, ys)
  np.testing.assert_allclose(one, out, rtol=1e-5, atol=1e-5)
  tiled = jax.tree_util.tree_map(lambda a: jnp.repeat(a, 3, 0), cond.inputs)
  np.testing.assert_allclose(shared, apply(ys, tiled), rtol=1e-5, atol=1e-5)
  del latent


def test_training_anchors_each_agent_on_the_proposal_its_logged_future_took(scene_example):
  """The stage-2 loss with anchors: finite, and the new projection learns."""
  from pcdiff_jax.model import encoder
  from pcdiff_jax.training import diffusion_stage
  anchored = dataclasses.replace(CFG, diffusion=dataclasses.replace(
      CFG.diffusion, denoiser=dataclasses.replace(CFG.diffusion.denoiser, anchor_inputs=True)))
  enc = encoder.init(jax.random.key(0), scene_example.feats, CFG.encoder)
  stats = diffusion_stage.fit_latent(enc, anchored, scene_example, 1, batch_size=1)
  cond = jax.jit(lambda f: planner.condition(enc, stats, f, anchored))(scene_example.feats)
  one = jax.tree_util.tree_map(lambda a: a[0], cond.inputs)
  params = denoiser_lib.init(jax.random.key(1), cond.mu[0], jnp.int32(0), one, anchored.diffusion.denoiser)
  out = params["params"]["out"]["kernel"]   # zero at init, which would stop every gradient below it
  params = {"params": {**params["params"], "out": {
      "kernel": 0.1 * jax.random.normal(jax.random.key(3), out.shape), "bias": params["params"]["out"]["bias"]}}}
  extra = {"encoder": enc, "stats": stats}
  loss_fn = lambda p: diffusion_stage.diffusion_loss(p, extra, scene_example, jax.random.key(2), anchored)[0]
  loss, grads = jax.jit(jax.value_and_grad(loss_fn))(params)
  assert np.isfinite(float(loss))
  assert float(jnp.abs(grads["params"]["in_anchor"]["kernel"]).max()) > 0


def _train(argv):
  from experiments import train
  return train.main(argv)


def test_train_cli_rejects_bad_input(tmp_path, capsys):
  bad = tmp_path / "bad.tfrecord"
  bad.write_bytes(b"not a tfrecord")
  assert _train(["--stage", "encoder", "--config", "tiny", "--data", str(bad), "--workdir",
                 str(tmp_path / "w"), "--no-progress"]) == 2
  assert "bad.tfrecord" in capsys.readouterr().err
  assert _train(["--stage", "encoder", "--config", "tiny", "--data", str(tmp_path / "none-*"),
                 "--workdir", str(tmp_path / "w"), "--no-progress"]) == 2
  with pytest.raises(SystemExit):
    _train(["--stage", "nope", "--data", "x", "--workdir", "w"])


def test_resume_accepts_a_run_saved_before_a_new_config_field(tmp_path):
  """A checkpoint whose config lacks a field added since (saved before the option
  existed) resumes when the field is at its default, and is refused when not."""
  import dataclasses
  import optax
  from pcdiff_jax import config as config_lib
  from pcdiff_jax.training import trainer
  cfg = get_config("tiny")
  state = trainer.create_state({"w": jnp.ones(3)}, optax.sgd(0.1), seed=0)
  saved = config_lib.to_dict(cfg)
  del saved["encoder"]["lane_inputs"]                      # as written by an older version
  ckpt = trainer.Checkpointer(str(tmp_path))
  ckpt.save(state.replace(step=jnp.asarray(3, jnp.int32)), saved)
  restored = ckpt.restore_or_keep(state, config_lib.to_dict(cfg))
  assert int(restored.step) == 3
  changed = dataclasses.replace(cfg, encoder=dataclasses.replace(cfg.encoder, lane_inputs=True))
  with pytest.raises(trainer.CheckpointMismatch, match="encoder.lane_inputs"):
    ckpt.restore_or_keep(state, config_lib.to_dict(changed))
  ckpt.close()


def test_fitted_targets_leave_out_a_path_the_latent_cannot_hold(scene_example):
  """With `target_fit_sigma`, the targets follow the logged positions; an
  agent whose log runs sideways to its box (a heading unrelated to the motion)
  gets a fit far outside the latent's spread and, with `target_max_rms`, is
  not trained on, while the agents that drive along their heading are."""
  import dataclasses
  from pcdiff_jax.model import encoder, latent
  from pcdiff_jax.training import diffusion_stage
  # A latent with a spread: the scene's logged actions and smooth variations of them.
  actions, _ = diffusion_stage.logged_actions(scene_example, CFG)
  horizon = actions.shape[-2]
  wave = np.sin(np.pi * np.linspace(0, 1, horizon)[:, None] * np.arange(1, 5))          # (T, 4)
  coef = np.random.default_rng(0).normal(size=(300, 2, 4)) * np.array([1.0, 0.05])[:, None]
  stats = latent.fit(np.concatenate([np.asarray(actions[0, :1]), np.einsum("nck,tk->ntc", coef, wave)]), 6)
  tg = scene_example.targets
  sideways = tg.future_xy[0, 1, :, ::-1]                       # along +y, box heading +x
  batch = scene_example.replace(targets=tg.replace(future_xy=tg.future_xy.at[0, 1].set(sideways)))
  fit = dataclasses.replace(CFG, diffusion=dataclasses.replace(CFG.diffusion, target_fit_sigma=1.0,
                                                               target_max_rms=3.0))
  speed = planner.agent_speed(batch.feats)
  targets = jax.jit(lambda b, c: diffusion_stage.latent_targets(b, stats, speed, c), static_argnums=1)
  (y_proj, full_proj), (y_fit, full_fit) = targets(batch, CFG), targets(batch, fit)
  rms = np.asarray(latent.whitened_rms(y_fit, stats))[0]
  assert bool(full_proj[0, 1]) and not bool(full_fit[0, 1]) and rms[1] > 3.0
  kept = np.asarray(full_proj[0]) & (np.arange(full_proj.shape[1]) != 1)
  assert kept.sum() >= 2 and np.array_equal(np.asarray(full_fit[0]), kept)
  err = lambda y: np.asarray(jnp.linalg.norm(latent.rollout(y, speed, stats, CFG.kinematics)[..., :2]
                                             - batch.targets.future_xy, axis=-1).mean(-1))[0]
  assert np.all(err(y_fit)[kept] <= err(y_proj)[kept] + 0.05)
