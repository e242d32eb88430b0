"""Guidance costs and latent-space guides: finite gradients, and J goes down."""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pcdiff_jax.model import guidance as G
from pcdiff_jax.sim import road_field

T = 40
# The toy latent is a shift in metres: steps of at most 1 m.
CFG = G.GuidanceConfig(mode="objective", w_map=1.0, eta=0.5, inner_steps=5, coll_horizon=T, map_stride=2, max_step=1.0)


def _agents(num=3, valid=None, pursuer=-1, evader=-1):
  valid = jnp.ones(num, bool) if valid is None else jnp.asarray(valid)
  return G.Agents(length=jnp.full(num, 4.5), width=jnp.full(num, 2.0), valid=valid,
                  vehicle=jnp.ones(num, bool), pursuer=jnp.int32(pursuer), evader=jnp.int32(evader))


def _road(half_width=4.0, empty=False):
  """Two straight road edges along x at y = -w and y = +w (road on their left)."""
  x = jnp.linspace(-100.0, 100.0, 201)
  lower = jnp.stack([x, jnp.full_like(x, -half_width)], -1)              # direction +x: road at +y
  upper = jnp.stack([x[::-1], jnp.full_like(x, half_width)], -1)         # direction -x: road at -y
  xy = jnp.concatenate([lower, upper])
  d = jnp.concatenate([jnp.tile(jnp.array([[1.0, 0.0]]), (201, 1)), jnp.tile(jnp.array([[-1.0, 0.0]]), (201, 1))])
  ids = jnp.concatenate([jnp.zeros(201, jnp.int32), jnp.ones(201, jnp.int32)])
  return road_field.from_edges(xy, d, ids, jnp.full(402, not empty), jnp.zeros(2), size=201, spacing=1.0)


def _poses(base_xy):
  """A toy 'decoder': latent (A, 2) shifts each agent's whole path."""
  def poses(y):
    xy = base_xy + y[:, None, :]
    return xy, jnp.zeros(xy.shape[:-1])
  return poses


def _straight(y0s, speeds, x0s):
  t = jnp.arange(T) * 0.1
  return jnp.stack([jnp.stack([x0 + v * t, jnp.full_like(t, y0)], -1)
                    for x0, y0, v in zip(x0s, y0s, speeds)])                 # (A, T, 2)


def test_map_and_collision_costs_are_zero_for_a_clean_scene_and_positive_otherwise():
  base = _straight([-1.5, 1.5, -1.5], [10.0, 10.0, 10.0], [0.0, 0.0, -60.0])
  agents, road = _agents(), _road()
  xy, yaw = _poses(base)(jnp.zeros((3, 2)))
  assert float(jnp.sum(G.map_cost(xy, yaw, agents, road, CFG))) == 0.0
  assert float(jnp.sum(G.collision_cost(xy, yaw, agents, CFG))) == 0.0
  off = _poses(base)(jnp.array([[0.0, -3.0], [0.0, 0.0], [0.0, 0.0]]))
  assert float(G.map_cost(*off, agents, road, CFG)[0]) > 0
  stacked = _poses(base)(jnp.array([[0.0, 2.0], [0.0, 0.0], [0.0, 0.0]]))   # agents 0, 1 side by side, touching
  coll = G.collision_cost(*stacked, agents, CFG)
  assert float(coll[0]) > 0 and float(coll[1]) > 0 and float(coll[2]) == 0.0


def test_map_excursion_is_how_far_a_corner_gets_past_the_edge():
  """Edges at y = +-4: a car 2 m wide centred on y = -1.5 stays 1.5 m inside; shifted 3 m
  off its lower corners are 1.5 m past the edge; a padded agent or a non-vehicle reads -inf."""
  base = _straight([-1.5, 1.5, -1.5], [10.0, 10.0, 10.0], [0.0, 0.0, -60.0])
  xy, yaw = _poses(base)(jnp.array([[0.0, -3.0], [0.0, 0.0], [0.0, 0.0]]))
  agents = dataclasses.replace(_agents(valid=[True, True, False]), vehicle=jnp.array([True, True, True]))
  out = np.asarray(G.map_excursion(xy, yaw, agents, _road(), CFG))
  np.testing.assert_allclose(out[:2], [1.5, -1.5], atol=0.15)
  assert out[2] == -np.inf
  walker = dataclasses.replace(agents, vehicle=jnp.array([False, True, True]))
  assert float(G.map_excursion(xy, yaw, walker, _road(), CFG)[0]) == -np.inf


@pytest.mark.parametrize("case", ["coincident", "padded", "empty_map", "all_padded"])
def test_gradients_are_finite_everywhere(case):
  base = _straight([0.0, 0.0, 0.0], [10.0, 10.0, 0.0], [0.0, 0.0, 0.0])   # 0 and 1 coincide
  valid = {"padded": [True, True, False], "all_padded": [False] * 3}.get(case, [True] * 3)
  agents = _agents(valid=valid, pursuer=1, evader=0)
  road = _road(empty=case == "empty_map")
  poses = _poses(base)

  def total(y):
    xy, yaw = poses(y)
    return (jnp.sum(G.objective(xy, yaw, agents, road, CFG)) + G.pursuit_cost(xy, agents, CFG))
  g = jax.grad(total)(jnp.zeros((3, 2)))
  assert np.isfinite(np.asarray(g)).all()
  if case == "all_padded":
    assert float(jnp.abs(g).sum()) == 0.0


def test_objective_guide_lowers_the_objective():
  # Agent 0 drifts off the road and into agent 1.
  base = _straight([-1.5, 1.5], [10.0, 10.0], [0.0, 0.0])
  agents, road = _agents(2), _road()
  poses = _poses(base)
  y0 = jnp.array([[0.0, 2.2], [0.0, 0.0]])                              # overlapping side by side
  y_off = jnp.array([[0.0, -3.5], [0.0, 0.0]])                          # off the lower edge
  guide = G.objective_guide(poses, agents, road, CFG)
  for y in (y0, y_off):
    before = float(jnp.sum(G.objective(*poses(y), agents, road, CFG)))
    after = float(jnp.sum(G.objective(*poses(guide(y, None, 0, 0)), agents, road, CFG)))
    assert before > 0 and after < 0.5 * before, (before, after)


def test_objective_guide_leaves_padded_agents_alone():
  base = _straight([-1.5, 1.5, 1.5], [10.0, 10.0, 10.0], [0.0, 0.0, 0.0])
  agents = _agents(valid=[True, True, False])
  y = jnp.array([[0.0, 2.2], [0.0, 0.0], [0.0, 5.0]])
  out = G.objective_guide(_poses(base), agents, _road(), CFG)(y, None, 0, 0)
  np.testing.assert_array_equal(np.asarray(out[2]), np.asarray(y[2]))


def test_adversarial_guide_moves_the_pursuer_toward_the_evader():
  base = _straight([-1.5, 1.5, -1.5], [10.0, 10.0, 10.0], [0.0, -10.0, -40.0])
  agents, road = _agents(pursuer=1, evader=0), _road()
  cfg = dataclasses.replace(CFG, mode="adversarial", w_pursue=10.0, eta=0.05, ibr_rounds=2)
  poses = _poses(base)
  y = jnp.zeros((3, 2))
  out = G.adversarial_guide(poses, agents, road, cfg)(y, None, 0, 0)
  before = float(G.pursuit_cost(poses(y)[0], agents, cfg))
  moved = np.asarray(out)
  pursuer_only = jnp.asarray(np.where(np.arange(3)[:, None] == 1, moved, 0.0))
  assert float(G.pursuit_cost(poses(pursuer_only)[0], agents, cfg)) < before   # pursuer closes in
  evader_only = jnp.asarray(np.where(np.arange(3)[:, None] == 0, moved, 0.0))
  assert float(G.pursuit_cost(poses(evader_only)[0], agents, cfg)) > before    # evader gets away
  assert not np.allclose(moved[1], 0.0)


def test_guide_steps_are_the_last_ones_and_bad_configs_are_refused():
  assert G.GuidanceConfig(guided_steps=2).guide_steps(5).tolist() == [False, False, False, True, True]
  assert G.GuidanceConfig(guided_steps=9).guide_steps(3).all()
  with pytest.raises(ValueError, match="mode"):
    G.GuidanceConfig(mode="magic").validate()
  with pytest.raises(ValueError, match="inner_steps"):
    G.GuidanceConfig(inner_steps=0).validate()


def test_agent_objective_is_one_row_of_the_objective():
  base = _straight([-1.5, 1.5, -3.5], [10.0, 10.0, 8.0], [0.0, 0.0, -3.0])   # overlaps and an excursion
  agents, road = _agents(valid=[True, True, True]), _road()
  xy, yaw = _poses(base)(jnp.array([[0.0, 1.0], [0.0, 0.0], [0.0, 0.0]]))
  full = G.objective(xy, yaw, agents, road, CFG)
  assert float(jnp.min(full)) > 0
  for slot in range(3):
    np.testing.assert_allclose(float(G.agent_objective(xy, yaw, agents, road, CFG, jnp.int32(slot))),
                               float(full[slot]), rtol=1e-5)
  assert float(G.agent_objective(xy, yaw, agents, road, CFG, jnp.int32(-1))) == 0.0


def test_collision_cost_over_nearest_neighbours_equals_all_pairs():
  # 12 agents in a 3 x 4 block, packed so that each touches up to 8 others
  # (sides and diagonals); neighbours are ranked by centre distance, which puts
  # a non-touching agent ahead of touching diagonal ones here, so k = 10.
  grid = np.stack(np.meshgrid(np.arange(3) * 3.5, np.arange(4) * 1.8, indexing="ij"), -1).reshape(-1, 2)
  t = jnp.arange(T) * 0.1
  xy = jnp.asarray(grid, jnp.float32)[:, None, :] + jnp.stack([8.0 * t, 0.0 * t], -1)
  yaw = jnp.zeros(xy.shape[:-1])
  agents = _agents(12, valid=[True] * 11 + [False])
  c = G._circles(xy, yaw, agents, CFG)
  r = agents.width / 2
  pair = agents.valid[:, None] & agents.valid[None, :] & ~jnp.eye(12, dtype=bool)
  every = jnp.broadcast_to(c[None], (12,) + c.shape)                        # all agents as neighbours
  brute = jnp.sum(jnp.where(pair, G._pair_overlaps(c, every, r, jnp.broadcast_to(r, (12, 12)),
                                                   CFG.coll_margin), 0.0), -1)
  assert float(jnp.min(brute[:11])) > 0 and float(brute[11]) == 0.0
  for k in (10, 11):
    near = G.collision_cost(xy, yaw, agents, dataclasses.replace(CFG, coll_neighbors=k))
    np.testing.assert_allclose(np.asarray(near), np.asarray(brute), rtol=1e-5)


def test_map_weight_defaults_per_mode_and_an_explicit_weight_wins():
  assert G.GuidanceConfig(mode="objective").map_weight == 100.0
  assert G.GuidanceConfig(mode="adversarial").map_weight == 1.0
  assert G.GuidanceConfig(mode="objective", w_map=3.0).map_weight == 3.0
  with pytest.raises(ValueError, match="w_map"):
    G.GuidanceConfig(mode="objective", w_map=-1.0).validate()


def test_collision_weight_defaults_per_mode_and_weighs_the_objective():
  assert G.GuidanceConfig(mode="objective").coll_weight == 10.0        # RESULTS' collision-weight ablation
  assert G.GuidanceConfig(mode="adversarial").coll_weight == 1.0       # Table III's setting
  assert G.GuidanceConfig(mode="objective", w_coll=0.5).coll_weight == 0.5
  with pytest.raises(ValueError, match="w_coll"):
    G.GuidanceConfig(mode="objective", w_coll=-1.0).validate()
  base = _straight([-1.5, 1.5, -1.5], [10.0, 10.0, 10.0], [0.0, 0.0, -60.0])
  stacked = _poses(base)(jnp.array([[0.0, 2.0], [0.0, 0.0], [0.0, 0.0]]))   # agents 0, 1 touching
  agents, road = _agents(), _road()
  coll = G.collision_cost(*stacked, agents, CFG)
  cost = lambda cfg: G.objective(*stacked, agents, road, cfg)
  default = dataclasses.replace(CFG, w_coll=None)
  np.testing.assert_allclose(cost(default) - cost(dataclasses.replace(CFG, w_coll=0.0)), 10.0 * coll, rtol=1e-5)
