"""The paper's closed-loop metrics of a rollout, per scenario and aggregated.

Per rolled-out scenario (`score_rollout`, jit-able, vmap over scenarios):
- collision and off-road counts (`sim.metrics.event_counts`);
- realism histograms: counts of longitudinal acceleration, lateral
  acceleration and jerk over the evaluated agents and the simulated steps
  (after the start step), of the rollout and of the log for the same agents
  and steps, on the fixed bin edges of `data.realism.FIXED_BIN_EDGES`;
- each evaluated agent's ADE to its log over the simulated steps where both
  are valid;
- still agents moved (`still_moved`): an evaluated agent is *still* when its
  log stays within `STILL_LOG_M` (1 m) of its start position (the log's at
  the start step) at every valid logged step of the window (start step to
  start + num_steps); it *moved* when its simulated position is more than
  `MOVED_SIM_M` (2 m) from that start position at some valid simulated step
  of the window. Parked and queued cars must not be driven away.

Aggregated (`aggregate`, host side): collision rate, off-road rate, realism =
the mean over the three quantities of W1 between the L1-normalised histograms
(generated vs logged, summed over all scenarios first), minADE = the mean over
agents of the smallest ADE over the N stochastic rollouts of a scenario (also
per kind: vehicles, pedestrians, cyclists),
still_moved_rate = moved still agents / still agents over every rollout (0
for log replay by construction).

Adversarial runs add (`adversarial_scores`, `aggregate_adversarial`): the
ego-adversary collision rate (their boxes overlap at a simulated step), the
adversary's off-road rate (a vehicle on the road at the start that leaves
it), the minimum over time of the ego-adversary centre distance, and the
impact speed (their relative speed at the first contact, over collisions).
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.data import realism
from pcdiff_jax.sim import metrics as sim_metrics
from pcdiff_jax.sim.datatypes import Array, ObjectType, SimulatorState
from pcdiff_jax.sim.selection import nearest_to_sdc

REALISM_QUANTITIES = ("lon_accel", "lat_accel", "jerk")
ADE_KINDS = (("vehicle", ObjectType.VEHICLE), ("pedestrian", ObjectType.PEDESTRIAN),
             ("cyclist", ObjectType.CYCLIST))   # minADE is also reported per kind
STILL_LOG_M = 1.0   # m: an agent is still when its log stays this close to its start position
MOVED_SIM_M = 2.0   # m: a still agent moved when the rollout takes it this far from it


@struct.dataclass
class RolloutScores:
  """One rollout of one scenario (any leading batch dims).

  events: EventCounts; hist_sim, hist_log: (3, K) counts per quantity of
  REALISM_QUANTITIES (K = the largest bin count; shorter rows are 0-padded);
  ade: (O,) per object; ade_valid: (O,) evaluated and with a valid step.
  controlled: (O,) objects the actor controlled, valid at the start step;
  lost: (O,) of those, the ones invalid at a later simulated step (an actor
  that drops an agent makes it vanish: it must stay 0); log_following: (O,)
  objects valid at the start that no actor controlled (they replay the log).
  still: (O,) evaluated agents still in the log; still_moved: (O,) of those,
  the ones moved more than 2 m in closed loop (`still_moved`). object_type: (O,)
  `ObjectType` values, for minADE per kind.
  """
  events: sim_metrics.EventCounts
  hist_sim: Array
  hist_log: Array
  ade: Array
  ade_valid: Array
  controlled: Array
  lost: Array
  log_following: Array
  still: Array
  still_moved: Array
  object_type: Array
  adversarial: Optional["AdversarialScores"] = None


@struct.dataclass
class AdversarialScores:
  """One rollout (any leading batch dims): has_pair () bool, an adversary and
  an ego valid at the start; collided, became_offroad () bool; min_distance ()
  m; impact_speed () m/s at the first contact (0 without one)."""
  has_pair: Array
  collided: Array
  became_offroad: Array
  min_distance: Array
  impact_speed: Array


def adversarial_scores(final_state: SimulatorState, start_step: int, adversary: Array,
                       max_road_edge_points: int) -> AdversarialScores:
  """Safety scores of the ego (SDC) against the adversary (object slot, -1:
  none) over the simulated steps. Unbatched."""
  sim = final_state.sim_trajectory
  ego = jnp.argmax(final_state.object_metadata.is_sdc)
  adv = jnp.maximum(adversary, 0)
  pair = jax.tree_util.tree_map(lambda a: jnp.stack([a[ego], a[adv]])[:, start_step:], sim)  # (2, T')
  has_pair = (adversary >= 0) & (adversary != ego) & pair.valid[0, 0] & pair.valid[1, 0]
  both = pair.valid[0] & pair.valid[1]                                    # (T',)
  after = jnp.arange(both.shape[0]) > 0
  contact = sim_metrics.pairwise_overlap(pair)[:, 0, 1] & both & after      # (T',)
  first = jnp.argmax(contact)
  rel_vel = pair.vel_xy[1, first] - pair.vel_xy[0, first]
  dist = jnp.linalg.norm(pair.xy[1] - pair.xy[0], axis=-1)
  min_distance = jnp.min(jnp.where(both & after, dist, jnp.inf))
  adv_traj = jax.tree_util.tree_map(lambda a: a[1:2], pair)
  off = sim_metrics.offroad(adv_traj, final_state.roadgraph_points, max_road_edge_points)[0]
  is_vehicle = final_state.object_metadata.object_types[adv] == 1
  collided = has_pair & jnp.any(contact)
  return AdversarialScores(
      has_pair=has_pair, collided=collided,
      became_offroad=has_pair & is_vehicle & ~off[0] & jnp.any(off[1:]),
      min_distance=jnp.where(has_pair, min_distance, jnp.inf),
      impact_speed=jnp.where(collided, jnp.linalg.norm(rel_vel), 0.0))


def aggregate_adversarial(scores: AdversarialScores) -> dict[str, float]:
  """Rates and means over every rollout with an ego-adversary pair."""
  has = np.asarray(scores.has_pair).reshape(-1)
  pick = lambda a: np.asarray(a).reshape(-1)[has]
  n = int(has.sum())
  collided = pick(scores.collided)
  finite = pick(scores.min_distance)
  finite = finite[np.isfinite(finite)]
  return {
      "num_pairs": n,
      "ego_adv_collision_rate": float(collided.mean()) if n else float("nan"),
      "adv_offroad_rate": float(pick(scores.became_offroad).mean()) if n else float("nan"),
      "min_distance": float(finite.mean()) if finite.size else float("nan"),
      "impact_speed": float(pick(scores.impact_speed)[collided].mean()) if collided.any() else float("nan"),
  }


def _num_bins() -> int:
  return max(len(realism.FIXED_BIN_EDGES[q]) - 1 for q in REALISM_QUANTITIES)


def _hist_counts(traj, mask) -> Array:
  feats = realism.motion_features(traj)
  k = _num_bins()
  rows = []
  for q in REALISM_QUANTITIES:
    edges = jnp.asarray(realism.FIXED_BIN_EDGES[q])
    c = realism.histogram_counts(feats[q], feats[q + "_valid"] & mask, edges)
    rows.append(jnp.pad(c, (0, k - c.shape[0])))
  return jnp.stack(rows)


def evaluated_agents(final_state: SimulatorState, start_step: int, max_agents: int) -> Array:
  """(O,) the agents scored: up to `max_agents` nearest the SDC at the start step."""
  return nearest_to_sdc(final_state.replace(timestep=jnp.int32(start_step)), max_agents)


def still_moved(final_state: SimulatorState, start_step: int, num_steps: int,
                evaluated: Array) -> tuple[Array, Array]:
  """(O,) still agents and (O,) those of them moved, of one scenario.

  Over the steps start_step .. start_step + num_steps: still = evaluated,
  valid at the start, and its logged position within STILL_LOG_M of the
  log's start position at every valid logged step (max displacement < 1 m);
  moved = still and its simulated position more than MOVED_SIM_M from that
  start position at some valid simulated step (max displacement > 2 m).
  evaluated: (O,) bool. Log replay moves none by construction.
  """
  sim, log = final_state.sim_trajectory, final_state.log_trajectory
  t = jnp.arange(sim.num_timesteps)
  window = (t >= start_step) & (t <= start_step + num_steps)               # (T,)
  start_xy = log.xy[:, start_step]                                          # (O, 2)
  log_disp = jnp.linalg.norm(log.xy - start_xy[:, None], axis=-1)           # (O, T)
  sim_disp = jnp.linalg.norm(sim.xy - start_xy[:, None], axis=-1)
  log_max = jnp.max(jnp.where(log.valid & window, log_disp, 0.0), -1)
  sim_max = jnp.max(jnp.where(sim.valid & window, sim_disp, 0.0), -1)
  still = evaluated & log.valid[:, start_step] & (log_max < STILL_LOG_M)
  return still, still & (sim_max > MOVED_SIM_M)


def score_rollout(final_state: SimulatorState, start_step: int, num_steps: int, max_agents: int,
                  max_road_edge_points: int) -> RolloutScores:
  """Scores of one rolled-out scenario (unbatched; vmap for batches)."""
  sim, log = final_state.sim_trajectory, final_state.log_trajectory
  evaluated = evaluated_agents(final_state, start_step, max_agents)
  at_start = sim.valid[:, start_step]
  log_following = at_start & ~final_state.object_metadata.is_controlled
  events = sim_metrics.event_counts(sim, log, final_state.roadgraph_points,
                                    final_state.object_metadata.object_types, evaluated, start_step,
                                    max_road_edge_points, max_evaluated=max_agents,
                                    replayed=log_following)
  t = jnp.arange(sim.num_timesteps)
  steps = (t > start_step) & (t <= start_step + num_steps)                  # (T,)
  mask = evaluated[:, None] & steps[None]                                    # (O, T)
  both = sim.valid & log.valid & mask
  dist = jnp.sqrt((sim.x - log.x) ** 2 + (sim.y - log.y) ** 2)
  count = jnp.sum(both, -1)
  ade = jnp.sum(jnp.where(both, dist, 0.0), -1) / jnp.maximum(count, 1)
  controlled, lost = lost_agents(final_state, start_step, num_steps)
  still, moved = still_moved(final_state, start_step, num_steps, evaluated & at_start)
  return RolloutScores(events=events, hist_sim=_hist_counts(sim, mask),
                       hist_log=_hist_counts(log, mask), ade=ade, ade_valid=count > 0,
                       controlled=controlled, lost=lost,
                       log_following=log_following,
                       still=still, still_moved=moved,
                       object_type=final_state.object_metadata.object_types)


def lost_agents(final_state: SimulatorState, start_step: int, num_steps: int) -> tuple[Array, Array]:
  """(O,) the controlled objects valid at the start step, and (O,) those of
  them invalid at some simulated step after it. The controlled set is the
  final state's `is_controlled` (`sim.step` records it; actors fix it at init)."""
  sim = final_state.sim_trajectory
  t = jnp.arange(sim.num_timesteps)
  steps = (t > start_step) & (t <= start_step + num_steps)                  # (T,)
  controlled = final_state.object_metadata.is_controlled & sim.valid[:, start_step]
  return controlled, controlled & jnp.any(steps[None] & ~sim.valid, -1)


def realism_w1(hist_sim: np.ndarray, hist_log: np.ndarray) -> dict[str, float]:
  """W1 per quantity and their mean, from summed (3, K) counts."""
  out = {}
  for i, q in enumerate(REALISM_QUANTITIES):
    edges = np.asarray(realism.FIXED_BIN_EDGES[q])
    k = len(edges) - 1
    p, r = np.asarray(hist_sim[i, :k], np.float64), np.asarray(hist_log[i, :k], np.float64)
    p, r = p / max(p.sum(), 1.0), r / max(r.sum(), 1.0)
    out[f"w1_{q}"] = float(realism.wasserstein_1(p, r, edges))
  out["realism"] = float(np.mean([out[f"w1_{q}"] for q in REALISM_QUANTITIES]))
  return out


def aggregate(scores: RolloutScores) -> dict[str, float]:
  """Metrics over scores with batch dims (S scenarios, N rollouts): rates over
  every rollout, realism from the summed histograms, minADE over the N."""
  rates = sim_metrics.EventCounts(**{k: jnp.asarray(v) for k, v in
                                     vars(scores.events).items()}).rates()
  ade = np.where(scores.ade_valid, scores.ade, np.inf)                     # (S, N, O)
  min_ade = ade.min(1)                                                     # (S, O)
  scored = np.isfinite(min_ade)
  out = dict(rates)
  out.update(realism_w1(np.sum(scores.hist_sim, axis=(0, 1)), np.sum(scores.hist_log, axis=(0, 1))))
  out["min_ade"] = float(min_ade[scored].mean()) if scored.any() else float("nan")
  out["num_ade_agents"] = int(scored.sum())
  kind = np.asarray(scores.object_type)[:, 0]                              # (S, O)
  for name, value in ADE_KINDS:
    of_kind = scored & (kind == value)
    out[f"min_ade_{name}"] = float(min_ade[of_kind].mean()) if of_kind.any() else float("nan")
    out[f"num_ade_{name}"] = int(of_kind.sum())
  out["controlled_agents"] = int(np.sum(scores.controlled))
  out["lost_agents"] = int(np.sum(scores.lost))
  out["log_following_agents"] = int(np.sum(scores.log_following))
  num_still = int(np.sum(scores.still))
  out["num_still_agents"] = num_still
  out["still_moved_rate"] = float(np.sum(scores.still_moved)) / num_still if num_still else float("nan")
  if scores.adversarial is not None:
    out.update(aggregate_adversarial(scores.adversarial))
  return out


_PER_OBJECT = ("ade", "ade_valid", "controlled", "lost", "log_following", "still", "still_moved",
               "object_type")


def concatenate_scores(parts: list[RolloutScores]) -> RolloutScores:
  """Scores of several calls along the scenario axis. Calls whose scenes hold
  more objects (a scene over 128 objects loads at 256) have a longer object
  axis: the per-object fields are padded with zeros (not evaluated, not
  controlled), which leaves every rate and mean of `aggregate` unchanged."""
  width = max(np.shape(p.ade)[-1] for p in parts)
  pad = lambda a: np.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, width - a.shape[-1])])
  parts = [p.replace(**{k: pad(np.asarray(getattr(p, k))) for k in _PER_OBJECT}) for p in parts]
  return jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *parts)
