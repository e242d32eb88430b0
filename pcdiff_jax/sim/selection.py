"""Which objects a policy controls and the metrics evaluate."""
from __future__ import annotations

import jax.numpy as jnp

from pcdiff_jax.sim.datatypes import Array, SimulatorState


def nearest_to_sdc(state: SimulatorState, max_agents: int, include_sdc: bool = False) -> Array:
  """(..., O) bool: up to `max_agents` objects valid at the current step,
  nearest the SDC first (the SDC itself excluded unless `include_sdc`).

  Padded sizes are fixed, so this never changes shapes: a rank test, no
  boolean indexing.
  """
  current = state.current_sim_trajectory                  # (..., O, 1)
  valid = current.valid[..., 0]
  is_sdc = state.object_metadata.is_sdc
  xy = current.xy[..., 0, :]                                # (..., O, 2)
  sdc_xy = jnp.sum(jnp.where(is_sdc[..., None], xy, 0.0), axis=-2, keepdims=True)
  dist = jnp.linalg.norm(xy - sdc_xy, axis=-1)
  eligible = valid & (include_sdc | ~is_sdc)
  dist = jnp.where(eligible, dist, jnp.inf)
  if include_sdc:
    dist = jnp.where(is_sdc & valid, -1.0, dist)  # the SDC always comes first
  rank = jnp.argsort(jnp.argsort(dist, axis=-1), axis=-1)
  return eligible & (rank < max_agents)
