"""Lane-relative inputs (model.lane_context) and loading a denoiser or an encoder trained without them."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from conftest import make_scene
from pcdiff_jax.config import get_config
from pcdiff_jax.model import denoiser, encoder, features, lane_context, planner

CFG = get_config("tiny")


def _slot(feats, obj):
  return int(np.flatnonzero(np.asarray(feats.agent_index) == obj)[0])


def test_lane_and_road_edge_inputs_of_agents_on_a_straight_road():
  """make_scene: one lane centre on y = 0 along +x, road edges at y = +-4.
  Object 0 (y = -2) sees its lane 2 m to its left at every look-ahead, the
  edges 6 m left and 2 m right; object 2 (y = -6.5, off the road) has no lane
  within reach and no edge on its right; padded slots are zero."""
  state = make_scene(num_steps=31).replace(timestep=jnp.int32(10))
  feats = jax.jit(lambda s: features.scene_features(s, CFG.features))(state)
  x = np.asarray(jax.jit(lane_context.lane_inputs)(feats))
  assert x.shape == (CFG.features.max_agents, lane_context.LANE_DIM)
  sdc = x[_slot(feats, 0)]
  for k, ahead in enumerate(lane_context.LOOKAHEAD):
    point, heading, found = sdc[5 * k:5 * k + 2], sdc[5 * k + 2:5 * k + 4], sdc[5 * k + 4]
    assert found == 1.0
    np.testing.assert_allclose(point, [ahead / 10.0, 0.2], atol=0.06)   # the nearest of points 0.5 m apart
    np.testing.assert_allclose(heading, [1.0, 0.0], atol=1e-5)
  np.testing.assert_allclose(sdc[-4:], [0.6, 1.0, 0.2, 1.0], atol=1e-5)   # left 6 m, right 2 m
  off = x[_slot(feats, 2)]
  assert off[4] == 0.0 and not off[:4].any()                              # lane 6.5 m away: none
  np.testing.assert_allclose(off[-4:], [0.25, 1.0, 1.0, 0.0], atol=1e-5)  # left edge 2.5 m, no right edge
  padded = ~np.asarray(feats.agent_valid)
  assert padded.any() and not x[padded].any()


def test_a_model_trained_without_lane_inputs_loads_with_them_unchanged(tiny_models):
  """`denoiser.with_new_inputs` adds the zero-initialised projection: the
  extended model's output equals the original's until it is trained."""
  with_lanes = dataclasses.replace(CFG, diffusion=dataclasses.replace(
      CFG.diffusion, denoiser=dataclasses.replace(CFG.diffusion.denoiser, lane_inputs=True)))
  state = make_scene(num_steps=31).replace(timestep=jnp.int32(10))
  params = denoiser.with_new_inputs(tiny_models.denoiser, with_lanes.diffusion.denoiser)
  assert denoiser.with_new_inputs(params, with_lanes.diffusion.denoiser) is not None
  assert "in_lane" not in tiny_models.denoiser["params"] and "in_lane" in params["params"]

  def out(cfg, den):
    @jax.jit
    def run(state):
      feats = jax.tree_util.tree_map(lambda a: a[None], features.scene_features(state, cfg.features))
      cond = planner.condition(tiny_models.encoder, tiny_models.stats, feats, cfg)
      y = cond.mu + 0.5
      return denoiser.apply(den, y, jnp.int32(40), cond.inputs, cfg.diffusion.denoiser), cond.inputs.agent_lane
    return run(state)
  before, no_lanes = out(CFG, tiny_models.denoiser)
  after, lanes = out(with_lanes, params)
  assert no_lanes.shape[-1] == 0 and lanes.shape[-1] == lane_context.LANE_DIM and np.abs(lanes).sum() > 0
  np.testing.assert_allclose(np.asarray(after), np.asarray(before), atol=1e-5)


def test_an_encoder_trained_without_lane_inputs_loads_with_them_unchanged(tiny_models):
  """`encoder.with_new_inputs` (SIMPL-AR's encoder, `finetune --policy simpl-ar
  --lane-inputs`): the same proposals until trained, and the new projections
  get a gradient, so training can use the lane inputs."""
  cfg = dataclasses.replace(CFG.encoder, lane_inputs=True)
  state = make_scene(num_steps=31).replace(timestep=jnp.int32(10))
  feats = jax.jit(lambda s: features.scene_features(s, CFG.features))(state)
  params = encoder.with_new_inputs(tiny_models.encoder, cfg)
  assert {"in_lane", "head_lane"} <= set(params["params"]) and "in_lane" not in tiny_models.encoder["params"]
  like = jax.eval_shape(lambda: encoder.init(jax.random.key(0), feats, cfg))
  assert jax.tree_util.tree_structure(like) == jax.tree_util.tree_structure(params)
  run = jax.jit(encoder.apply, static_argnums=2)
  before, after = run(tiny_models.encoder, feats, CFG.encoder), run(params, feats, cfg)
  np.testing.assert_allclose(np.asarray(after.trajectories), np.asarray(before.trajectories), atol=1e-5)
  np.testing.assert_allclose(np.asarray(after.probs), np.asarray(before.probs), atol=1e-6)
  grad = jax.jit(jax.grad(lambda p: jnp.sum(encoder.apply(p, feats, cfg).trajectories ** 2)))(params)["params"]
  assert float(jnp.abs(grad["head_lane"]["kernel"]).sum()) > 0


def _exhaustive(feats) -> np.ndarray:
  """lane_inputs by brute force over every segment of every map piece (numpy), one scene."""
  f = jax.tree_util.tree_map(np.asarray, feats)
  c, d = f.map_dir[:, None, 0], f.map_dir[:, None, 1]
  pts = np.stack([f.map_center[:, None, 0] + c * f.map_points[..., 0] - d * f.map_points[..., 1],
                  f.map_center[:, None, 1] + d * f.map_points[..., 0] + c * f.map_points[..., 1]], -1)
  start, end = pts[:, :-1].reshape(-1, 2), pts[:, 1:].reshape(-1, 2)
  kind = np.repeat(np.where(f.map_valid, f.map_kind, -1), pts.shape[1] - 1)
  out = np.zeros((f.agent_valid.shape[0], lane_context.LANE_DIM), np.float32)
  for i in np.flatnonzero(f.agent_valid):
    rot = np.array([[f.agent_dir[i, 0], f.agent_dir[i, 1]], [-f.agent_dir[i, 1], f.agent_dir[i, 0]]])
    a, b = (start - f.agent_center[i]) @ rot.T, (end - f.agent_center[i]) @ rot.T
    seg = b - a
    length2 = np.maximum((seg ** 2).sum(-1), 1e-9)
    heading = seg / np.sqrt(length2)[:, None]
    aligned = (kind == features.MapKind.LANE) & (heading[:, 0] >= 0.5)
    row = []
    for ahead in lane_context.LOOKAHEAD:
      q = np.array([ahead, 0.0])
      u = np.clip(((q - a) * seg).sum(-1) / length2, 0, 1)
      p = a + u[:, None] * seg
      gap2 = np.where(aligned, ((p - q) ** 2).sum(-1), np.inf)
      j = int(np.argmin(gap2))
      ok = gap2[j] <= 36.0
      row += list(p[j] / 10.0 * ok) + list(heading[j] * ok) + [float(ok)]
    sx = np.where(np.abs(seg[:, 0]) > 1e-6, seg[:, 0] ** 2, np.inf)
    u = np.clip(-a[:, 0] * seg[:, 0] / sx, 0, 1)
    beside = a + u[:, None] * seg
    near = (kind == features.MapKind.ROAD_EDGE) & (np.abs(beside[:, 0]) <= 4.0)
    for side in (1.0, -1.0):
      lateral = np.where(near & (side * beside[:, 1] > 0), side * beside[:, 1], np.inf)
      m = lateral.min()
      row += [min(m / 10.0, 1.0) if np.isfinite(m) else 1.0, float(np.isfinite(m))]
    out[i] = row
  return out


def test_the_nearest_pieces_search_matches_brute_force(real_state):
  """lane_inputs searches the 16 map pieces nearest each query, not every
  segment: on a synthetic scene it is exact; on the real WOMD record (dense
  intersection maps, cpu features) at most one agent in 20 may differ."""
  from pcdiff_jax import sim
  cpu = get_config("cpu")
  fast = jax.jit(lane_context.lane_inputs)
  state = make_scene(num_steps=31).replace(timestep=jnp.int32(10))
  feats = jax.jit(lambda s: features.scene_features(s, CFG.features))(state)
  np.testing.assert_allclose(np.asarray(fast(feats)), _exhaustive(feats), atol=1e-4)
  feats = jax.jit(lambda s: features.scene_features(s, cpu.features))(sim.reset(real_state))
  got, want = np.asarray(fast(feats)), _exhaustive(feats)
  valid = np.asarray(feats.agent_valid)
  differs = (np.abs(got - want).max(-1) > 1e-4) & valid
  assert valid.sum() > 40 and differs.sum() <= valid.sum() // 20, np.flatnonzero(differs)
