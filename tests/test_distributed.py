"""pcdiff_jax.distributed: data-parallel training and scenario-parallel
evaluation on 4 fake CPU devices give the one-device numbers.

XLA fixes the CPU device count when JAX starts its backend, and a pytest
worker starts it with one device, so the 4-device checks run once, in a fresh
interpreter with XLA_FLAGS set (the `four_devices` fixture runs `_worker`
below); it writes what it measured as JSON and the tests compare. Kept small:
trainer.fit on a small regression (the stages' step and loop), the cv
baseline over 4 synthetic scenes of 20 steps. The tiny scene encoder's curve
and the tiny learned policy's rollouts (about a minute more of compiles) run
with PCDIFF_SLOW_TESTS=1.
"""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from pcdiff_jax import distributed

ROOT = Path(__file__).resolve().parents[1]
DEVICES = 4
STEPS = 6
BATCH = 8
SLOW = os.environ.get("PCDIFF_SLOW_TESTS") == "1"


@pytest.fixture(scope="module")
def four_devices(tmp_path_factory) -> dict:
  out = tmp_path_factory.mktemp("four_devices")
  # XLA's backend optimisations off: the programs compile faster and run a few steps.
  flags = (f" --xla_force_host_platform_device_count={DEVICES} --xla_backend_optimization_level=0"
           " --xla_llvm_disable_expensive_passes=true")
  env = dict(os.environ, JAX_PLATFORMS="cpu", TF_CPP_MIN_LOG_LEVEL="2",
             XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") + flags).strip())
  code = "import sys; sys.path[:0] = ['tests', '.']; import test_distributed as t; t._worker(sys.argv[1])"
  proc = subprocess.run([sys.executable, "-c", code, str(out)], cwd=ROOT, env=env, capture_output=True,
                        text=True, timeout=900)
  assert proc.returncode == 0, proc.stderr[-4000:]
  return json.loads((out / "result.json").read_text())


@pytest.mark.slow
def test_data_parallel_training_gives_the_one_device_loss_curve(four_devices):
  t = four_devices["train"]
  assert len(t["one_device"]) == STEPS and np.all(np.isfinite(t["one_device"]))
  assert t["one_device"][-1] < t["one_device"][0]                      # it learns
  np.testing.assert_allclose(t["four_devices"], t["one_device"], rtol=1e-5)
  # Interrupted on 4 devices, resumed on 2 and interrupted, finished on 1: the same curve.
  np.testing.assert_allclose(t["resumed_4_2_1"], t["one_device"], rtol=1e-5)
  assert t["checkpoints"] == [2, 4, STEPS]
  assert t["sharding"] == {"params": "P()", "params_devices": DEVICES, "opt_state": "P()",
                           "batch": "P('data',)", "batch_rows_per_device": BATCH // DEVICES}


@pytest.mark.slow
def test_sharded_evaluation_gives_the_one_device_results(four_devices):
  r = four_devices["rollout"]
  assert r["devices"] == [1, DEVICES]
  one, four = r["runs"]
  assert one["per_scenario"] == four["per_scenario"] and len(one["per_scenario"]) == 4
  for key in ("collision_rate", "offroad_rate", "min_ade", "realism"):
    assert one[key] == pytest.approx(four[key], rel=1e-6, abs=1e-9), key


@pytest.mark.skipif(not SLOW, reason="about a minute of compiles: PCDIFF_SLOW_TESTS=1")
def test_real_stage_and_learned_policy_on_four_devices(four_devices):
  t = four_devices["encoder_stage"]
  np.testing.assert_allclose(t["four_devices"], t["one_device"], rtol=1e-4)
  r = four_devices["learned"]
  # The tiny learned policy (untrained) with a key per rollout: the same plans.
  np.testing.assert_allclose(r["xy"][1], r["xy"][0], rtol=1e-5, atol=1e-4)
  assert r["moved"] > 0.1


@pytest.mark.slow
def test_cli_refuses_a_batch_that_does_not_split(four_devices):
  assert four_devices["cli"]["train_batch_3"] == 2
  assert "multiple of the 4 device(s)" in four_devices["cli"]["train_batch_3_err"]
  assert four_devices["cli"]["rollout_batch_3"] == 2


def test_one_host_helpers():
  mesh = distributed.data_mesh()
  assert mesh.axis_names == ("data",) and mesh.devices.size == jax.device_count()
  assert distributed.host_shard(["a", "b", "c"]) == ["a", "b", "c"]   # one process holds every file
  assert distributed.local_batch_size(4, distributed.data_mesh(1)) == 4
  with pytest.raises(ValueError, match="device"):
    distributed.data_mesh(jax.device_count() + 1)
  assert distributed.initialize() is False   # no coordinator: the single-host run


def test_device_flags_are_checked(tmp_path, capsys):
  from experiments import rollout, train
  with pytest.raises(SystemExit) as err:
    train.main(["--data", "x", "--workdir", str(tmp_path / "w"), "--devices", "0"])
  assert err.value.code == 2 and "--devices must be >= 1" in capsys.readouterr().err
  with pytest.raises(SystemExit) as err:
    train.main(["--data", "x", "--workdir", str(tmp_path / "w"), "--num-processes", "2", "--process-id", "2"])
  assert err.value.code == 2 and "--process-id" in capsys.readouterr().err
  too_many = str(jax.device_count() + 1)
  assert rollout.main(["--scenarios", "x", "--out", str(tmp_path / "o"), "--devices", too_many]) == 2
  assert f"{too_many} device(s) asked for" in capsys.readouterr().err


# ----------------------------------------------------------------------------
# The 4-device side, run in a fresh interpreter by the `four_devices` fixture.


def _worker(out_dir: str) -> None:
  jax.config.update("jax_compilation_cache_dir", str(ROOT / ".cache" / "jax"))
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
  assert jax.device_count() == DEVICES, jax.devices()
  out = Path(out_dir)
  scenes = _write_scenes(out / "scenes.tfrecord")
  result = {"train": _train_curves(out), "rollout": _rollouts(scenes, out), "cli": _cli(scenes, out)}
  if SLOW:
    result.update(encoder_stage=_encoder_stage_curves(out), learned=_learned_rollouts(scenes))
  (out / "result.json").write_text(json.dumps(result))


def _regression():
  """A small MLP regression with input dropout (so the step's key matters):
  (params, loss_fn, 64 examples as numpy)."""
  import jax.numpy as jnp
  rng = np.random.default_rng(0)
  x = rng.normal(size=(64, 8)).astype(np.float32)
  examples = {"x": x, "y": np.sin(x @ rng.normal(size=8)).astype(np.float32)}
  params = {"w1": (rng.normal(size=(8, 16)) / 3).astype(np.float32), "b1": np.zeros(16, np.float32),
            "w2": (rng.normal(size=(16,)) / 4).astype(np.float32)}   # numpy: each run donates its own copy

  def loss_fn(p, batch, key):
    keep = jax.random.bernoulli(key, 0.9, batch["x"].shape)   # (B, 8), drawn over the global batch
    h = jnp.tanh(jnp.where(keep, batch["x"], 0.0) / 0.9 @ p["w1"] + p["b1"])
    loss = jnp.mean((h @ p["w2"] - batch["y"]) ** 2)
    return loss, {"loss": loss}
  return params, loss_fn, examples


def _train_curves(out: Path) -> dict:
  """trainer.fit on 1 device, on 4, and interrupted (as by Ctrl-C) on 4,
  resumed on 2 and interrupted, finished on 1."""
  from pcdiff_jax.config import TrainConfig
  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import trainer
  tc = TrainConfig(batch_size=BATCH, learning_rate=3e-2, warmup_steps=2, total_steps=STEPS, log_every=1,
                   checkpoint_every=100)
  params, loss_fn, examples = _regression()
  tx = trainer.make_optimizer(tc)

  def run(workdir, mesh, stop_at=None):
    rows = tc.batch_size if mesh is None else distributed.local_batch_size(tc.batch_size, mesh)

    def batch_at(step):
      if step == stop_at:
        raise KeyboardInterrupt
      return data_lib.batch_at(examples, step, rows, tc.seed)
    try:
      state, _ = trainer.fit(trainer.create_state(params, tx, tc.seed),
                             trainer.make_train_step(loss_fn, tx, mesh=mesh), batch_at, None, tc,
                             str(workdir), {"train": "regression"}, progress=False, mesh=mesh)
    except KeyboardInterrupt:
      return None
    return state

  def losses(workdir):
    rows = [json.loads(line) for line in open(workdir / "metrics.jsonl")]
    return [r["train/loss"] for r in rows if "train/loss" in r]

  run(out / "one", None)
  state = run(out / "four", distributed.data_mesh(DEVICES))
  checkpoints = []
  for mesh, stop in ((distributed.data_mesh(DEVICES), 2), (distributed.data_mesh(2), 4), (None, None)):
    run(out / "resumed", mesh, stop)
    ckpt = trainer.Checkpointer(str(out / "resumed"), read_only=True)
    checkpoints.append(ckpt.latest_step())
    ckpt.close()
  batch = distributed.shard_batch(data_lib.batch_at(examples, 0, BATCH, 0), distributed.data_mesh(DEVICES))
  leaf = lambda tree: jax.tree_util.tree_leaves(tree)[0]
  return {"one_device": losses(out / "one"), "four_devices": losses(out / "four"),
          "resumed_4_2_1": losses(out / "resumed"), "checkpoints": checkpoints,
          "sharding": {"params": str(leaf(state.params).sharding.spec),
                       "params_devices": len(leaf(state.params).sharding.device_set),
                       "opt_state": str(leaf(state.opt_state).sharding.spec),
                       "batch": str(leaf(batch).sharding.spec),
                       "batch_rows_per_device": leaf(batch).addressable_shards[0].data.shape[0]}}


def _encoder_stage_curves(out: Path) -> dict:
  """The tiny scene encoder (stage 1) on make_scene examples: 1 device against 4."""
  from conftest import make_scene

  from pcdiff_jax.config import get_config
  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import encoder_stage
  cfg = get_config("tiny")
  cfg = dataclasses.replace(cfg, encoder_train=dataclasses.replace(
      cfg.encoder_train, batch_size=DEVICES, total_steps=4, checkpoint_every=100))
  fn = jax.jit(lambda s: data_lib.example_at(s, 10, cfg.features, cfg.encoder.horizon))
  exs = [fn(make_scene(num_steps=91, speeds=(10.0 + i, 8.0 - 0.5 * i, 0.0, 5.0 + i))) for i in range(8)]
  ex = jax.tree_util.tree_map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *exs)
  curves = {}
  for name, mesh in (("one_device", None), ("four_devices", distributed.data_mesh(DEVICES))):
    encoder_stage.train(cfg, ex, None, str(out / f"enc_{name}"), progress=False, mesh=mesh)
    rows = [json.loads(line) for line in open(out / f"enc_{name}" / "encoder" / "metrics.jsonl")]
    curves[name] = [r["train/loss"] for r in rows if "train/loss" in r]
  return curves


def _write_scenes(path: Path) -> str:
  from pcdiff_jax.data import womd
  from pcdiff_jax.data.synthetic import SyntheticConfig, generate_scene
  cfg = SyntheticConfig(max_rg_points=4000)
  womd.write(str(path), [(s.state, s.scenario_id) for s in (generate_scene(0, i, cfg) for i in range(4))])
  return str(path)


def _rollouts(scenes: str, out: Path) -> dict:
  """evaluation.evaluate of the cv baseline, 4 scenes per call: 1 device, then 4."""
  from pcdiff_jax import evaluation
  from pcdiff_jax.config import MetricsConfig
  cfg = evaluation.EvalConfig(method="cv", batch_size=4, num_steps=20, gifs=0,
                              metrics=MetricsConfig(max_reactive_agents=8, max_road_edge_points=512))
  runs, devices = [], []
  for n, mesh in ((1, None), (DEVICES, distributed.data_mesh(DEVICES))):
    s = evaluation.evaluate(scenes, str(out / f"cv{n}"), cfg, progress=False, mesh=mesh)
    rows = [json.loads(line) for line in open(out / f"cv{n}" / "scenarios.jsonl")]
    devices.append(s["devices"])
    runs.append({"per_scenario": rows, **{k: s[k]["mean"] for k in ("collision_rate", "offroad_rate",
                                                                      "min_ade", "realism")}})
  return {"devices": devices, "runs": runs}


def _learned_rollouts(scenes: str):
  """The tiny learned policy's closed loop over 4 scenes, 2 rollouts each
  with their own keys (8 per call): one device against 4."""
  from conftest import build_tiny_models

  from pcdiff_jax import evaluation, policy
  from pcdiff_jax.config import MetricsConfig, get_config
  from pcdiff_jax.data import womd
  metrics = MetricsConfig(max_reactive_agents=8, max_road_edge_points=512)
  cfg = evaluation.EvalConfig(method="pcdiff", num_steps=5, metrics=metrics)
  model_cfg = evaluation.with_agent_cap(get_config("tiny"), metrics)
  actor = policy.actor(model_cfg, policy.PolicyConfig(ddim_steps=2, warm_start=False))
  models = build_tiny_models()
  state, _ = next(womd.iterate(scenes, batch_size=4, with_meta=True))
  tiled = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a), 2, axis=0), state)
  rngs = jax.random.split(jax.random.PRNGKey(0), 8)
  xy = []
  for mesh in (None, distributed.data_mesh(DEVICES)):
    run = evaluation.make_rollout_fn(actor, cfg, mesh)
    args = (tiled, rngs, models) if mesh is None else (
        *jax.device_put((tiled, rngs), distributed.batch_sharded(mesh)), distributed.replicate(models, mesh))
    final = jax.device_get(run(*args))
    xy.append(np.stack([final.sim_trajectory.x, final.sim_trajectory.y], -1)[:, :, 10:16].tolist())
  a = np.asarray(xy[0])
  return {"xy": xy, "moved": float(np.abs(a[:, :, -1] - a[:, :, 0]).max())}


def _cli(scenes: str, out: Path) -> dict:
  import contextlib
  import io

  from experiments import rollout, train
  err = io.StringIO()
  with contextlib.redirect_stderr(err):
    code = train.main(["--config", "tiny", "--data", scenes, "--workdir", str(out / "cli"), "--batch-size", "3",
                       "--no-progress"])
  roll = rollout.main(["--scenarios", scenes, "--out", str(out / "cli_roll"), "--batch-size", "3",
                       "--no-progress"])
  return {"train_batch_3": code, "train_batch_3_err": err.getvalue(), "rollout_batch_3": roll}
