"""The paper's closed-loop metrics of a rollout, per scenario and aggregated.

Per rolled-out scenario (`score_rollout`, jit-able, vmap over scenarios):
- collision and off-road counts (`sim.metrics.event_counts`);
- realism histograms: counts of longitudinal acceleration, lateral
  acceleration and jerk over the evaluated agents and the simulated steps
  (after the start step), of the rollout and of the log for the same agents
  and steps, on the fixed bin edges of `data.realism.FIXED_BIN_EDGES`;
- each evaluated agent's ADE to its log over the simulated steps where both
  are valid.

Aggregated (`aggregate`, host side): collision rate, off-road rate, realism =
the mean over the three quantities of W1 between the L1-normalised histograms
(generated vs logged, summed over all scenarios first), minADE = the mean over
agents of the smallest ADE over the N stochastic rollouts of a scenario.
"""
from __future__ import annotations

import numpy as np
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.data import realism
from pcdiff_jax.sim import metrics as sim_metrics
from pcdiff_jax.sim.datatypes import Array, SimulatorState
from pcdiff_jax.sim.selection import nearest_to_sdc

REALISM_QUANTITIES = ("lon_accel", "lat_accel", "jerk")


@struct.dataclass
class RolloutScores:
  """One rollout of one scenario (any leading batch dims).

  events: EventCounts; hist_sim, hist_log: (3, K) counts per quantity of
  REALISM_QUANTITIES (K = the largest bin count; shorter rows are 0-padded);
  ade: (O,) per object; ade_valid: (O,) evaluated and with a valid step.
  """
  events: sim_metrics.EventCounts
  hist_sim: Array
  hist_log: Array
  ade: Array
  ade_valid: Array


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


def score_rollout(final_state: SimulatorState, start_step: int, num_steps: int, max_agents: int,
                  max_road_edge_points: int) -> RolloutScores:
  """Scores of one rolled-out scenario (unbatched; vmap for batches)."""
  sim, log = final_state.sim_trajectory, final_state.log_trajectory
  evaluated = evaluated_agents(final_state, start_step, max_agents)
  events = sim_metrics.event_counts(sim, log, final_state.roadgraph_points,
                                    final_state.object_metadata.object_types, evaluated, start_step,
                                    max_road_edge_points, max_evaluated=max_agents)
  t = jnp.arange(sim.num_timesteps)
  steps = (t > start_step) & (t <= start_step + num_steps)                  # (T,)
  mask = evaluated[:, None] & steps[None]                                    # (O, T)
  both = sim.valid & log.valid & mask
  dist = jnp.sqrt((sim.x - log.x) ** 2 + (sim.y - log.y) ** 2)
  count = jnp.sum(both, -1)
  ade = jnp.sum(jnp.where(both, dist, 0.0), -1) / jnp.maximum(count, 1)
  return RolloutScores(events=events, hist_sim=_hist_counts(sim, mask),
                       hist_log=_hist_counts(log, mask), ade=ade, ade_valid=count > 0)


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
  return out
