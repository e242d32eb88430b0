"""The SIMPL-style scene encoder: shapes, masking, invariances, gradients."""
from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene, stack_states
from pcdiff_jax.config import get_config
from pcdiff_jax.model import encoder as E
from pcdiff_jax.model import features as F
from pcdiff_jax.sim import env

FCFG = get_config("tiny").features
ECFG = get_config("tiny").encoder
ALL_PAIRS = dataclasses.replace(ECFG, num_neighbors=0)
FEATURES = jax.jit(F.scene_features, static_argnums=1)
APPLY = jax.jit(E.apply, static_argnums=2)
INIT = jax.jit(E.init, static_argnums=2)


@pytest.fixture(scope="module")
def feats():
  """make_scene at t = 10: 4 real agents in 8 slots, 32 map pieces."""
  return FEATURES(env.reset(make_scene(), init_steps=11), FCFG)


@pytest.fixture(scope="module")
def params(feats):
  return INIT(jax.random.PRNGKey(0), feats, ECFG)


def agent_rows(out, rows):
  """The per-agent outputs of `rows`, as a dict of arrays."""
  return {k: np.asarray(getattr(out, k))[rows] for k in
          ("agent_tokens", "trajectories", "yaws", "logits", "probs")}


def test_output_shapes_and_probabilities(feats, params):
  out = APPLY(params, feats, ECFG)
  a, m, k, t, d = (FCFG.max_agents, FCFG.max_polylines, ECFG.num_modes, ECFG.horizon,
                   ECFG.d_model)
  chex.assert_shape(out.agent_tokens, (a, d))
  chex.assert_shape(out.map_tokens, (m, d))
  chex.assert_shape(out.context_tokens, (a + m, d))
  chex.assert_shape(out.trajectories, (a, k, t, 2))
  chex.assert_shape(out.yaws, (a, k, t))
  chex.assert_shape(out.control_points, (a, k, ECFG.bezier_degree + 1, 2))
  chex.assert_shape([out.logits, out.probs], (a, k))
  np.testing.assert_allclose(np.asarray(out.probs).sum(-1), 1.0, atol=1e-5)
  np.testing.assert_array_equal(out.context_valid, np.concatenate([feats.agent_valid,
                                                                   feats.map_valid]))
  for leaf in jax.tree_util.tree_leaves(out):
    assert np.isfinite(np.asarray(leaf, np.float64)).all()
  assert not np.asarray(out.trajectories)[~np.asarray(feats.agent_valid)].any()
  xy, yaw = E.proposals_to_world(out, feats)
  chex.assert_shape(xy, (a, k, t, 2))
  scene_xy, _ = E.proposals_to_scene(out, feats)
  chex.assert_shape(scene_xy, (a, k, t, 2))


def test_bezier_basis_and_yaw_follow_the_curve():
  basis, deriv = E.bezier_basis(5, 80)
  np.testing.assert_allclose(basis.sum(-1), 1.0, atol=1e-6)
  np.testing.assert_allclose(deriv.sum(-1), 0.0, atol=1e-4)
  ctrl = np.random.default_rng(0).normal(size=(6, 2)).astype(np.float32) * 10
  curve, vel = basis @ ctrl, deriv @ ctrl
  finite_diff = (curve[2:] - curve[:-2]) / (2 / 80)
  np.testing.assert_allclose(finite_diff, vel[1:-1], rtol=0.02, atol=0.3)   # O(h^2) error
  np.testing.assert_allclose(curve[-1], ctrl[-1], atol=1e-5)     # ends at the last point
  # A straight curve along +y: yaw pi/2 everywhere; a stationary one: yaw 0, finite grad.
  line = np.stack([np.zeros(6), np.linspace(0, 10, 6)], -1).astype(np.float32)
  np.testing.assert_allclose(E._heading(jnp.asarray(deriv @ line)), np.pi / 2, atol=1e-5)
  g = jax.grad(lambda c: jnp.sum(E._heading(jnp.asarray(deriv) @ c)))(jnp.zeros((6, 2)))
  assert np.isfinite(np.asarray(g)).all()


def test_proposals_start_at_the_agents_velocity(feats, params):
  """With anchor_velocity the first step of every proposal moves the agent
  by v dt along its heading (up to the curve's O(dt^2) bending), so the
  inverse dynamics of a proposal carries no first-step jump."""
  out = APPLY(params, feats, ECFG)
  valid = np.asarray(feats.agent_valid)
  speed = np.asarray(feats.agent_history)[:, -1, F.AGENT_CHANNELS.index("vel_x")][valid]
  first = np.asarray(out.trajectories)[valid][:, :, 0]                    # (n, K, 2)
  assert speed.max() > 1.0
  np.testing.assert_allclose(first[..., 0], np.broadcast_to(0.1 * speed[:, None], first.shape[:2]), atol=0.1)
  np.testing.assert_allclose(first[..., 1], 0.0, atol=0.1)
  ctrl = np.asarray(out.control_points)[valid]
  np.testing.assert_allclose(ctrl[:, :, 1, 0], np.broadcast_to(speed[:, None] * 8.0 / ECFG.bezier_degree, ctrl.shape[:2]), rtol=1e-5)


def test_padded_slots_do_not_change_valid_outputs(feats, params):
  out = APPLY(params, feats, ECFG)
  rng = np.random.default_rng(1)

  def junk(x, valid):   # garbage (and NaN) in every padded slot
    noise = rng.normal(size=x.shape).astype(np.float32) * 50
    noise.flat[0] = np.nan
    v = np.asarray(valid).reshape(valid.shape + (1,) * (x.ndim - valid.ndim))
    return jnp.where(v, x, noise)

  av = feats.agent_valid
  dirty = feats.replace(
      agent_history=junk(feats.agent_history, av), agent_center=junk(feats.agent_center, av),
      agent_dir=junk(feats.agent_dir, av),
      agent_history_valid=jnp.where(av[:, None], feats.agent_history_valid, True))
  out2 = APPLY(params, dirty, ECFG)
  rows = np.asarray(av)
  for k, v in agent_rows(out, rows).items():
    np.testing.assert_allclose(agent_rows(out2, rows)[k], v, atol=1e-5, err_msg=k)
  np.testing.assert_allclose(out2.map_tokens, out.map_tokens, atol=1e-5)
  # More padding (16 agent slots instead of 8) leaves the valid outputs as they
  # are, even when every token attends to every other (kNN edges never pick a
  # padded token while a valid one is left).
  wide = FEATURES(env.reset(make_scene(), init_steps=11),
                  dataclasses.replace(FCFG, max_agents=16))
  ref, out3 = APPLY(params, feats, ALL_PAIRS), APPLY(params, wide, ALL_PAIRS)
  for k, v in agent_rows(ref, rows).items():
    np.testing.assert_allclose(agent_rows(out3, np.arange(16) < 4)[k], v, atol=1e-4, err_msg=k)


def test_permuting_agents_permutes_outputs(feats, params):
  perm = np.array([2, 0, 3, 1, 4, 5, 6, 7])          # shuffles the 4 real agents
  agent_fields = ("agent_history", "agent_history_valid", "agent_valid", "agent_index",
                  "agent_types", "agent_center", "agent_dir")
  permuted = feats.replace(**{k: getattr(feats, k)[perm] for k in agent_fields})
  for cfg in (ALL_PAIRS, ECFG):
    out, out2 = APPLY(params, feats, cfg), APPLY(params, permuted, cfg)
    for k, v in agent_rows(out, perm).items():
      np.testing.assert_allclose(agent_rows(out2, np.arange(8))[k], v, atol=1e-4, err_msg=k)


def test_knn_edges_match_all_pairs_when_k_covers_every_token(feats, params):
  num_valid = int(feats.agent_valid.sum() + feats.map_valid.sum())   # 36 of 40 tokens
  out = APPLY(params, feats, ALL_PAIRS)
  knn = APPLY(params, feats, dataclasses.replace(ECFG, num_neighbors=num_valid))
  rows = np.asarray(feats.agent_valid)
  for k, v in agent_rows(out, rows).items():
    np.testing.assert_allclose(agent_rows(knn, rows)[k], v, atol=1e-4, err_msg=k)


def test_neighbours_mask_padded_tokens():
  centre = jnp.array([[0.0, 0.0], [1.0, 0.0], [5.0, 0.0], [2.0, 0.0]])
  valid = jnp.array([True, True, False, True])
  idx, mask = E.neighbours(centre, valid, 3)
  np.testing.assert_array_equal(idx[0], [0, 1, 3])
  np.testing.assert_array_equal(idx[2, 0], 2)          # padded receiver: itself first, masked
  assert not bool(mask[2, 0]) and bool(mask[0].all())
  # Fewer valid senders than k: the rest are masked.
  idx, mask = E.neighbours(centre, jnp.array([True, False, False, False]), 3)
  np.testing.assert_array_equal(mask[0], [True, False, False])


def test_relative_pose_is_frame_free():
  centre = jnp.array([[0.0, 0.0], [3.0, 4.0]])
  direction = jnp.array([[1.0, 0.0], [0.0, 1.0]])
  r = E.relative_pose(centre, direction, None, 100.0)  # all pairs
  np.testing.assert_allclose(r[0, 1], [0.05, 0.6, 0.8, 0.0, 1.0], atol=1e-6)
  np.testing.assert_allclose(r[1, 0], [0.05, -0.8, 0.6, 0.0, -1.0], atol=1e-6)
  np.testing.assert_allclose(r[0, 0, 1:3], [0.0, 0.0], atol=1e-6)   # self: no direction


def test_fully_padded_input_is_finite_with_finite_gradients(feats, params):
  empty = jax.tree_util.tree_map(jnp.zeros_like, feats)
  batch = stack_states([feats, empty])

  def loss(p):
    o = E.apply(p, batch, ECFG)
    mask = o.agent_valid[..., None, None, None]
    value = (jnp.sum(jnp.where(mask, o.trajectories, 0.0) ** 2) + jnp.sum(o.yaws ** 2)
             + jnp.sum(o.logits ** 2) + jnp.sum(o.map_tokens ** 2))
    return value, o

  grads, out = jax.jit(jax.grad(loss, has_aux=True))(params)
  chex.assert_shape(out.trajectories, (2, FCFG.max_agents, ECFG.num_modes, ECFG.horizon, 2))
  # The batched forward pass equals the unbatched one.
  single = APPLY(params, feats, ECFG)
  np.testing.assert_allclose(out.trajectories[0], single.trajectories, atol=1e-4)
  np.testing.assert_allclose(out.probs[0], single.probs, atol=1e-5)
  for leaf in jax.tree_util.tree_leaves(out):
    assert np.isfinite(np.asarray(leaf, np.float64)).all()
  np.testing.assert_allclose(np.asarray(out.probs).sum(-1), 1.0, atol=1e-5)
  leaves = jax.tree_util.tree_leaves(grads)
  assert all(np.isfinite(np.asarray(g)).all() for g in leaves)
  assert sum(float(jnp.abs(g).sum()) for g in leaves) > 0


def test_dropout_is_on_only_with_an_rng(feats, params):
  drop_cfg = dataclasses.replace(ECFG, dropout=0.3)
  a = APPLY(params, feats, drop_cfg, jax.random.PRNGKey(1))
  b = APPLY(params, feats, drop_cfg, jax.random.PRNGKey(2))
  assert np.isfinite(np.asarray(a.trajectories)).all()
  assert not np.allclose(a.trajectories, b.trajectories)


def test_world_proposals_follow_a_rigid_transform_of_the_scene(feats, params):
  from test_features import rigid_transform
  angle, shift = 0.7, np.array([30.0, -5.0])
  moved = FEATURES(rigid_transform(env.reset(make_scene(), init_steps=11), angle, shift), FCFG)
  out, out2 = APPLY(params, feats, ECFG), APPLY(params, moved, ECFG)
  rows = np.asarray(feats.agent_valid)
  for k, v in agent_rows(out, rows).items():   # the encoder sees the same scene
    np.testing.assert_allclose(agent_rows(out2, rows)[k], v, atol=1e-3, err_msg=k)
  xy, yaw = (np.asarray(a)[rows] for a in E.proposals_to_world(out, feats))
  xy2, yaw2 = (np.asarray(a)[rows] for a in E.proposals_to_world(out2, moved))
  rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
  np.testing.assert_allclose(xy2, xy @ rot.T + shift, atol=1e-3)
  np.testing.assert_allclose(np.angle(np.exp(1j * (yaw2 - yaw - angle))), 0.0, atol=1e-3)


def _sft_per_edge(params, h, e, idx, mask, layer: E.SFTLayer):
  """The SFT layer with its key and value projected on every edge (the textbook form)."""
  p = params["params"]
  dense = lambda name, x: x @ p[name]["kernel"] + p[name].get("bias", 0.0)
  def norm(name, x):
    mu, var = jnp.mean(x, -1, keepdims=True), jnp.var(x, -1, keepdims=True)
    return (x - mu) / jnp.sqrt(var + 1e-6) * p[name]["scale"] + p[name]["bias"]
  head = lambda name, x: jnp.einsum("...d,dhc->...hc", x, p[name]["kernel"]) + p[name]["bias"]
  mem = dense("mem_e", e) + dense("mem_i", h)[:, None] + E.senders(dense("mem_j", h), idx)
  mem = jax.nn.relu(norm("mem_ln", mem))
  q, key, val = head("query", h), head("key", mem), head("value", mem)
  logits = jnp.einsum("nhc,nkhc->nhk", q, key) / np.sqrt(q.shape[-1])
  weights = jax.nn.softmax(jnp.where(mask[:, None], logits, -1e9), -1)
  att = jnp.einsum("nhk,nkhc->nhc", weights, val).reshape(h.shape[0], -1)
  att = att @ p["out"]["kernel"].reshape(-1, h.shape[-1]) + p["out"]["bias"]
  h = norm("ln_att", h + att)
  h = norm("ln_ffn", h + dense("Dense_0", jax.nn.relu(dense("Dense_1", h))))   # Dense_0 is built first, outside
  if layer.update_edges:
    e = norm("edge_ln", e + jax.nn.relu(norm("edge_ln_in", dense("edge_upd", mem))))
  return h, e


@pytest.mark.parametrize("all_pairs", [False, True])
def test_sft_layer_is_attention_with_keys_and_values_on_every_edge(all_pairs):
  """Keys and values applied per receiver compute the per-edge layer, to float rounding, with
  the parameters `nn.DenseGeneral` would make (checkpoints load as they are)."""
  n, k, d = 12, 5, 16
  keys = jax.random.split(jax.random.PRNGKey(0), 5)
  h = jax.random.normal(keys[0], (n, d))
  if all_pairs:
    idx, mask = None, jnp.arange(n)[None, :].repeat(n, 0) < n - 2
    e = jax.random.normal(keys[1], (n, n, d))
  else:
    idx = jax.random.randint(keys[2], (n, k), 0, n)
    mask = jax.random.uniform(keys[3], (n, k)) > 0.3
    e = jax.random.normal(keys[1], (n, k, d))
  layer = E.SFTLayer(d, num_heads=4, ffn_multiplier=2, update_edges=True, dropout=0.0)
  params = layer.init(keys[4], h, e, idx, mask, True)
  assert params["params"]["key"]["kernel"].shape == (d, 4, d // 4)
  assert params["params"]["value"]["bias"].shape == (4, d // 4)
  params = jax.tree_util.tree_map(lambda a: a + 0.3 * jax.random.normal(keys[0], a.shape), params)
  got, want = layer.apply(params, h, e, idx, mask, True), _sft_per_edge(params, h, e, idx, mask, layer)
  for a, b in zip(got, want):
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-4)
