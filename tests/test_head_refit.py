"""The proposal-head refit: the cached trunk reproduces the encoder, only the head trains, the CLI's errors."""
from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax import config as config_lib
from pcdiff_jax.config import get_config
from pcdiff_jax.model import encoder
from pcdiff_jax.training import data as data_lib, head_refit

TINY = get_config("tiny")
CFG = dataclasses.replace(TINY, encoder=dataclasses.replace(TINY.encoder, lane_inputs=True))


@pytest.fixture(scope="module")
def examples():
  """Two scenes (make_scene, agents driving at different speeds) at t = 10, as numpy Examples."""
  fn = jax.jit(lambda s: data_lib.example_at(s, 10, CFG.features, CFG.encoder.horizon))
  exs = [fn(make_scene(num_steps=91, speeds=speeds)) for speeds in ((10.0, 8.0, 0.0, 5.0), (4.0, 12.0, 6.0, 0.0))]
  return jax.tree_util.tree_map(lambda *a: np.stack([np.asarray(x) for x in a]), *exs)


@pytest.fixture(scope="module")
def params(examples):
  first = jax.tree_util.tree_map(lambda a: a[0], examples.feats)
  p = encoder.init(jax.random.key(0), first, CFG.encoder)
  # Non-zero lane projections, so the test sees the lane path the head reads.
  lane = jax.tree_util.tree_map(lambda a: 0.05 * np.ones_like(a), p["params"]["head_lane"])
  return head_refit.with_head(p, {"head_lane": lane})


def test_head_on_cached_trunk_outputs_is_the_encoders(params, examples):
  trunk = head_refit.trunk_outputs(params, CFG, examples, batch_size=4)
  # Jitted: eager, the encoder would compile op by op.
  traj, logits = jax.jit(lambda h, t: head_refit.apply_head(h, CFG, t))(head_refit.head_params(params), trunk)
  out = jax.jit(lambda p, f: encoder.apply(p, f, CFG.encoder))(
      params, jax.tree_util.tree_map(np.asarray, examples.feats))
  valid = np.asarray(out.agent_valid)
  assert valid.sum() >= 6
  np.testing.assert_allclose(np.asarray(traj)[valid], np.asarray(out.trajectories)[valid], atol=1e-3)
  np.testing.assert_allclose(np.asarray(logits)[valid], np.asarray(out.logits)[valid], atol=1e-4)


def test_refit_trains_the_head_only_and_lowers_the_loss(params, examples, tmp_path):
  trunk = head_refit.trunk_outputs(params, CFG, examples, batch_size=4)
  tc = dataclasses.replace(CFG.encoder_train, total_steps=40, batch_size=4, learning_rate=3e-3,
                           warmup_steps=2, checkpoint_every=40, log_every=20)
  before = float(head_refit.loss(head_refit.head_params(params), CFG, trunk)[0])
  refit = head_refit.refit(params, CFG, [trunk, trunk], [0.5, 0.5], tc, str(tmp_path / "head"),
                           config_lib.to_dict(CFG), progress=False)
  after = float(head_refit.loss(head_refit.head_params(refit), CFG, trunk)[0])
  assert after < 0.8 * before
  for name, sub in params["params"].items():
    same = jax.tree_util.tree_all(jax.tree_util.tree_map(
        lambda a, b: bool(np.array_equal(np.asarray(a), np.asarray(b))), sub, refit["params"][name]))
    assert same == (name not in head_refit.HEAD_PARAMS), name
  m = head_refit.evaluate(head_refit.head_params(refit), CFG, trunk)
  assert m["count"] > 0 and np.isfinite(m["min_ade"]) and np.isfinite(m["speed_bias_1s"])
  padded = head_refit.evaluate(head_refit.head_params(refit), CFG, trunk, batch_size=3)   # 2 examples + 1 pad
  assert padded == pytest.approx(m, rel=1e-5)


def test_mixed_batches_take_each_sources_share(params, examples):
  trunk = head_refit.trunk_outputs(params, CFG, examples, batch_size=4)
  other = trunk.replace(speed=trunk.speed + 100.0)
  batch = head_refit.mixed_batch_at([trunk, other], [0.25, 0.75], step=3, batch_size=8, seed=0)
  from_other = (batch.speed.max(-1) >= 100.0)
  assert batch.speed.shape[0] == 8 and from_other.sum() == 6
  again = head_refit.mixed_batch_at([trunk, other], [0.25, 0.75], step=3, batch_size=8, seed=0)
  np.testing.assert_array_equal(batch.tokens, again.tokens)


def test_refit_cli_errors_name_the_input(tmp_path, capsys):
  from experiments import refit_head
  assert refit_head.main(["--from", str(tmp_path / "none"), "--data", "x.tfrecord",
                          "--workdir", str(tmp_path / "out")]) == 2
  err = capsys.readouterr().err
  assert str(tmp_path / "none") in err and "Traceback" not in err
  (tmp_path / "model" / "encoder").mkdir(parents=True)
  assert refit_head.main(["--from", str(tmp_path / "model"), "--data", "x.tfrecord",
                          "--workdir", str(tmp_path / "model")]) == 2
  assert "--workdir" in capsys.readouterr().err
