"""Shared fixtures: the real WOMD record (from ../shared) and tiny hand-built scenes."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

# Compiles dominate CPU test time; three XLA CPU settings cut them, to the same results up to
# float rounding. XLA splits each CPU program into parallel codegen parts by default: on 2 cores
# that two test workers already fill, the split costs more CPU than it saves. The older loop
# emitters compile faster than the fusion emitters. LLVM's optimisation level 1 compiles a tiny
# closed loop 2.1x faster than the default level (two tests of tests/test_policy.py, new cache:
# 52 s against 110 s); level 0 is faster still (39 s) but its compiled training step returns
# NaN gradients where the same ops run one by one do not (tests/test_trained_pipeline.py): not
# used. XLA_DEFAULTS_ENV=1 keeps XLA's defaults (tests/test_policy_package.py then compares to
# a tolerance, as on another CPU).
XLA_DEFAULTS_ENV = "PCDIFF_TEST_XLA_DEFAULTS"
TEST_XLA_FLAGS = ("--xla_cpu_parallel_codegen_split_count=1", "--xla_cpu_use_fusion_emitters=false",
                  "--xla_backend_optimization_level=1")
if os.environ.get(XLA_DEFAULTS_ENV) != "1":   # test workers and subprocesses inherit the changed flags
  set_flags = os.environ.get("XLA_FLAGS", "").split()
  os.environ["XLA_FLAGS"] = " ".join(set_flags + [f for f in TEST_XLA_FLAGS if f not in set_flags])

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
WOMD_RECORD = ROOT.parent / "shared" / "data" / "womd" / "motion_data_one_example.tfrecord"

# Compiles dominate CPU test time: keep them across runs.
jax.config.update("jax_compilation_cache_dir", str(ROOT / ".cache" / "jax"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")


@pytest.fixture(scope="session")
def womd_path() -> str:
  if not WOMD_RECORD.exists():
    pytest.skip(f"real WOMD sample not found at {WOMD_RECORD} (../shared is absent)")
  return str(WOMD_RECORD)


@pytest.fixture(scope="session")
def real_state(womd_path):
  from pcdiff_jax.data import womd
  state, _ = womd.load(womd_path)
  return state


@pytest.fixture(scope="session")
def tensorflow():
  """TensorFlow, the independent reference of the record tests; they skip without it (it is the
  optional `tf` extra; `make install` has it)."""
  return pytest.importorskip("tensorflow", reason="TensorFlow (the `tf` extra) is the independent reference here")


@pytest.fixture(scope="session")
def raw_example(womd_path, tensorflow):
  """The real record parsed independently of our loader: {key: np.ndarray}."""
  tf = tensorflow
  raw = next(iter(tf.data.TFRecordDataset(womd_path))).numpy()
  ex = tf.train.Example.FromString(raw)
  out = {}
  for key, feat in ex.features.feature.items():
    kind = feat.WhichOneof("kind")
    out[key] = np.array(getattr(feat, kind).value)
  return out


def make_scene(num_objects: int = 4, num_steps: int = 31, speeds=(10.0, 8.0, 0.0, 5.0),
               ys=(-2.0, 2.0, -6.5, -2.0), xs=(0.0, 0.0, 10.0, -30.0), half_width: float = 4.0):
  """A straight two-lane road along x (edges at y = +-half_width) with agents
  driving at constant speed. Object 0 is the SDC; object 2 starts off road.

  Returns an unbatched SimulatorState with timestep 0 and sim == log.
  """
  from pcdiff_jax.sim.datatypes import (ObjectMetadata, RoadgraphPoints, SimulatorState,
                                        TrafficLights, Trajectory)
  t = np.arange(num_steps) * 0.1
  speeds = np.asarray(speeds[:num_objects], np.float32)
  x = np.asarray(xs[:num_objects], np.float32)[:, None] + speeds[:, None] * t[None]
  y = np.broadcast_to(np.asarray(ys[:num_objects], np.float32)[:, None], x.shape)
  f = lambda a: jnp.asarray(np.ascontiguousarray(a), jnp.float32)
  shape = x.shape
  traj = Trajectory(
      x=f(x), y=f(y), z=f(np.zeros(shape)), vel_x=f(np.broadcast_to(speeds[:, None], shape)),
      vel_y=f(np.zeros(shape)), yaw=f(np.zeros(shape)), valid=jnp.ones(shape, bool),
      timestamp_micros=jnp.asarray(np.broadcast_to((t * 1e6).astype(np.int32), shape)),
      length=f(np.full(shape, 4.5)), width=f(np.full(shape, 2.0)), height=f(np.full(shape, 1.5)))
  # Road edges: the road lies on the left of each edge's direction.
  px = np.arange(-100.0, 200.0, 0.5, dtype=np.float32)
  n = px.size
  ex = np.concatenate([px, px[::-1], px])
  ey = np.concatenate([np.full(n, -half_width), np.full(n, half_width), np.zeros(n)])
  dx = np.concatenate([np.ones(n), -np.ones(n), np.ones(n)])
  types = np.concatenate([np.full(n, 15), np.full(n, 15), np.full(n, 2)])
  ids = np.concatenate([np.zeros(n), np.ones(n), np.full(n, 2)]).astype(np.int32)
  rg = RoadgraphPoints(x=f(ex), y=f(ey), z=f(np.zeros(3 * n)), dir_x=f(dx), dir_y=f(np.zeros(3 * n)),
                       dir_z=f(np.zeros(3 * n)), types=jnp.asarray(types, jnp.int32),
                       ids=jnp.asarray(ids), valid=jnp.ones(3 * n, bool))
  L = 2
  lights = TrafficLights(x=f(np.zeros((L, num_steps))), y=f(np.zeros((L, num_steps))),
                         z=f(np.zeros((L, num_steps))), state=jnp.full((L, num_steps), 6, jnp.int32),
                         lane_ids=jnp.full((L, num_steps), 2, jnp.int32),
                         valid=jnp.zeros((L, num_steps), bool).at[0].set(True))
  is_sdc = np.zeros(num_objects, bool)
  is_sdc[0] = True
  md = ObjectMetadata(ids=jnp.arange(num_objects, dtype=jnp.int32),
                      object_types=jnp.ones(num_objects, jnp.int32), is_sdc=jnp.asarray(is_sdc),
                      is_modeled=jnp.ones(num_objects, bool), is_valid=jnp.ones(num_objects, bool),
                      objects_of_interest=jnp.zeros(num_objects, bool),
                      is_controlled=jnp.zeros(num_objects, bool))
  return SimulatorState(sim_trajectory=traj, log_trajectory=traj, log_traffic_light=lights,
                        object_metadata=md, timestep=jnp.int32(0), roadgraph_points=rg)


@pytest.fixture(scope="session")
def tiny_models():
  """Untrained tiny models with a latent fitted on make_scene (weights do not
  matter where this is used)."""
  return build_tiny_models()


def build_tiny_models():
  """The `tiny_models` fixture's value (also for code run outside pytest)."""
  from pcdiff_jax.config import get_config
  from pcdiff_jax.model import denoiser as denoiser_lib
  from pcdiff_jax.model import encoder, planner
  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import diffusion_stage
  cfg = get_config("tiny")
  state = make_scene(num_steps=91)
  # Jitted: eager example building and encoding compile op by op (~50 s on CPU).
  ex = jax.jit(lambda s: jax.tree_util.tree_map(lambda a: a[None], data_lib.example_at(s, 10, cfg.features, 80)))(state)
  enc = encoder.init(jax.random.key(0), ex.feats, cfg.encoder)
  # make_scene's logs are straight at constant speed: fit on the (random)
  # proposals too, so that latents decode into actions of a real size.
  with_props = dataclasses.replace(cfg, diffusion=dataclasses.replace(cfg.diffusion, pca_proposal_weight=0.5))
  stats = diffusion_stage.fit_latent(enc, with_props, ex, 1, batch_size=1)
  cond = jax.jit(lambda e, st, f: planner.condition(e, st, f, cfg))(enc, stats, ex.feats)
  one = jax.tree_util.tree_map(lambda a: a[0], cond.inputs)
  den = denoiser_lib.init(jax.random.key(1), cond.mu[0], jnp.int32(0), one, cfg.diffusion.denoiser)
  return planner.Models(encoder=enc, denoiser=den, stats=stats)


@pytest.fixture
def scene():
  return make_scene()


def stack_states(states):
  return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *states)


# The files with the most compile work, longest first: `make test` hands whole files to its two
# workers in collection order (`--dist loadfile`), so a long file collected last would run alone
# at the end (docs/DEVELOPING.md, "Testing").
LONGEST_FIRST = ("test_trained_pipeline.py", "test_policy.py", "test_notebook.py", "test_wosac.py",
                 "test_policy_package.py")


def pytest_collection_modifyitems(config, items):
  rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
  items.sort(key=lambda item: rank.get(item.path.name, len(LONGEST_FIRST)))   # stable: file order kept
