"""Training: losses and metrics, batches, the train CLI (resume, config guard), both stages."""
from __future__ import annotations

import json
import os

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


def test_diffusion_loss_finite_with_masked_agents(scene_example):
  from pcdiff_jax.model import encoder, latent
  from pcdiff_jax.training import diffusion_stage
  enc = encoder.init(jax.random.key(0), scene_example.feats, CFG.encoder)
  stats = diffusion_stage.fit_latent(enc, CFG, scene_example, 1, batch_size=1)
  cond = planner.condition(enc, stats, scene_example.feats, CFG)
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
  out = denoiser_lib.apply(params, y, jnp.int32(50), cond.inputs, CFG.diffusion.denoiser)
  assert float(jnp.abs(out[0, 5:]).max()) == 0.0
  del latent


def _train(argv):
  from experiments import train
  return train.main(argv)


def test_train_cli_resume_guard_and_both_stages(tmp_path, womd_path, capsys):
  work = str(tmp_path / "w")
  base = ["--config", "tiny", "--data", womd_path, "--val-data", womd_path, "--workdir", work,
          "--no-progress"]
  assert _train(["--stage", "encoder", "--steps", "2"] + base) == 0
  assert _train(["--stage", "encoder", "--steps", "4"] + base) == 0     # resumes at 2
  lines = [json.loads(l) for l in open(os.path.join(work, "encoder", "metrics.jsonl"))]
  assert [d["step"] for d in lines if "train/loss" in d] == [1, 2, 3, 4]   # no step repeated
  assert any("val/min_fde" in d for d in lines)
  # TensorBoard event files hold the same scalars, tagged for its scalars plugin.
  import glob

  import tensorflow as tf
  from tensorflow.core.util import event_pb2
  tags = set()
  for f in glob.glob(os.path.join(work, "encoder", "tb", "*")):
    for rec in tf.data.TFRecordDataset(f):
      for v in event_pb2.Event.FromString(rec.numpy()).summary.value:
        tags.add((v.tag, v.metadata.plugin_data.plugin_name))
  assert ("train/loss", "scalars") in tags and ("val/min_fde", "scalars") in tags
  # Another model in the same workdir is refused with the differing fields named.
  assert _train(["--stage", "encoder", "--config", "cpu", "--data", womd_path, "--workdir", work,
                 "--no-progress", "--steps", "1"]) == 2
  assert "encoder.d_model" in capsys.readouterr().err
  # Stage 2, both variants, beside the same encoder.
  assert _train(["--stage", "diffusion", "--steps", "2"] + base) == 0
  assert _train(["--stage", "diffusion", "--steps", "2", "--no-prior"] + base) == 0
  summary = json.load(open(os.path.join(work, "diffusion_summary.json")))
  assert np.isfinite(summary["diffusion"]["val"]["min_ade"])
  from pcdiff_jax.training import diffusion_stage
  from pcdiff_jax.training import data as D
  models, cfg = diffusion_stage.load(work)
  assert cfg.encoder == CFG.encoder and cfg.diffusion == CFG.diffusion
  ex, _ = D.load_or_build(womd_path, diffusion_stage.encoder_stage.cache_spec(cfg),
                          os.path.join(work, "cache"), "val", progress=False)
  cond = planner.condition(models.encoder, models.stats, jax.tree_util.tree_map(jnp.asarray, ex.feats), cfg)
  for n in (1, 3):
    y0 = planner.sample(models.denoiser, cond, cfg, jax.random.key(0), n)
    states = planner.decode_states(models.stats, cond, y0, cfg)
    assert states.shape == (1, cfg.features.max_agents, cfg.encoder.horizon, 4)
    assert np.all(np.isfinite(np.asarray(states)))
  # Export as a shipped model: parameters only, loadable by the one-call loader.
  from experiments import export
  import pcdiff_jax
  shipped = str(tmp_path / "shipped")
  assert export.main(["--workdir", work, "--out", shipped]) == 0
  assert export.main(["--workdir", work, "--out", shipped]) == 2          # never overwrites
  assert "exists" in capsys.readouterr().err
  loaded, loaded_cfg = pcdiff_jax.pretrained(path=shipped)
  assert loaded_cfg == cfg
  for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(models)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  enc, _ = pcdiff_jax.pretrained(path=shipped, stage="encoder")
  assert jax.tree_util.tree_structure(enc) == jax.tree_util.tree_structure(models.encoder)
  with pytest.raises(FileNotFoundError, match="no shipped model"):
    pcdiff_jax.pretrained(path=str(tmp_path / "nothing"))
  # On-policy fine-tuning (CAT-K-style round) from the shipped folder: the
  # encoder and the denoiser move, the latent stays, and the result loads as a
  # model (both stages, so SIMPL-AR takes it too).
  from experiments import finetune
  ft = str(tmp_path / "ft")
  argv = ["--from", shipped, "--data", womd_path, "--workdir", ft, "--cache-dir", os.path.join(work, "cache"),
          "--scenes", "1", "--steps", "2", "--encoder-steps", "1", "--times", "12", "13", "--max-agents", "8",
          "--batch-size", "2", "--no-progress"]
  assert finetune.main(argv) == 0
  tuned, tuned_cfg = diffusion_stage.load(ft)
  assert tuned_cfg.diffusion == cfg.diffusion and tuned_cfg.encoder == cfg.encoder
  for a, b in zip(jax.tree_util.tree_leaves(tuned.stats), jax.tree_util.tree_leaves(models.stats)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  changed = lambda x, y: any(not np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
                             zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)))
  assert changed(tuned.denoiser, models.denoiser) and changed(tuned.encoder, models.encoder)
  enc_ft, _ = pcdiff_jax.pretrained(path=ft, stage="encoder")
  assert not changed(enc_ft, tuned.encoder)
  summary = json.load(open(os.path.join(ft, "finetune_summary.json")))
  assert summary["rounds"][0]["collect"]["examples"] == 2 and summary["rounds"][0]["step"] == 2
  assert finetune.main(argv) == 0                                         # finished rounds are kept
  assert finetune.main(argv[:1] + [str(tmp_path / "nothing")] + argv[2:]) == 2
  assert "no diffusion/" in capsys.readouterr().err


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
