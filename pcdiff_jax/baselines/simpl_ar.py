"""SIMPL-AR baseline: the stage-1 encoder's marginal proposals, made consistent.

At every replanning step: encode the scene, turn each agent's K = 6
proposals into actions (the flat inverse of `model.latent`) and roll them out
with f; choose one mode per agent that approximately minimises

    sum_i -log max(p_i(k_i), eps) + lambda * sum_{i<j} Coll_ij(k_i, k_j),

Coll_ij = the number of (step, circle pair) overlaps between the two rolled-out
plans over the first `lookahead` steps (each agent covered by 3 circles of
radius width / 2 along its length). The minimisation is iterated conditional
modes: start from each agent's most likely mode, then `sweeps` passes over
the agents, least confident (lowest top probability) first, each agent taking
its best mode given the others' current choices (every update can only lower
the objective). Then execute the
chosen plan by tracking it 0.5 s ahead (`tracking_action`: why not its
first inverse action), replanning at 10 Hz like ours.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import jax.numpy as jnp

from pcdiff_jax.config import Config
from pcdiff_jax.model import encoder, joint_selection, latent
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model import planner
from pcdiff_jax.sim import dynamics
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, Array


@dataclasses.dataclass(frozen=True)
class SimplARConfig:
  collision_weight: float = 10.0   # lambda
  lookahead: int = 30              # steps (3 s)
  sweeps: int = 2
  min_prob: float = 1e-3           # eps
  track_steps: int = 5             # the executed action tracks the chosen proposal 0.5 s ahead
  sample: bool = False             # draw the modes by their probabilities (Gumbel) instead of the top mode
  temperature: float = 1.0         # of the sampled modes' log-probabilities


def tracking_action(path: Array, speed: Array, cfg: SimplARConfig, dt: float = 0.1) -> Array:
  """[a, psi_dot] (A, 2) that track agent-frame paths (A, T, 2) from [0, 0, 0, speed]:
  reach the path's speed at step j = track_steps within j steps, steer by pure
  pursuit towards its point at step j.

  Why not the path's first inverse action: SIMPL's Bezier head pins a
  proposal's start to the agent's position but not to its velocity, so the
  first step carries a speed and heading jump; executed at every 10 Hz
  replanning, that jump becomes a constant push (measured: agents spinning
  and leaving the road). Tracking a point 0.5 s ahead follows the proposal
  without its first-step artefact.
  """
  j = cfg.track_steps
  return dynamics.pure_pursuit(path[:, j - 1], path[:, j - 2], speed, j, dt)


collision_counts = joint_selection.collision_counts   # kept here: SIMPL-AR's objective


def select_modes(probs: Array, coll: Array, valid: Array, cfg: SimplARConfig,
                 rng: Optional[Array] = None) -> Array:
  """Iterated conditional modes on the joint objective. probs (A, K) -> modes (A,).

  With `cfg.sample` (and an rng) the unary term is -log p / temperature minus
  Gumbel noise: without collisions each agent's mode is then a draw from its
  probabilities (the Gumbel-max trick), so repeated rollouts differ; with
  collisions ICM resolves them around that draw."""
  unary = -jnp.log(jnp.maximum(probs, cfg.min_prob))                         # (A, K)
  if cfg.sample and rng is not None:
    unary = unary / cfg.temperature - jax.random.gumbel(rng, unary.shape)
  # The least confident agents yield first: a confident agent keeps its mode
  # unless the others cannot get out of its way.
  order = jnp.argsort(jnp.max(probs, -1))
  return joint_selection.iterated_conditional_modes(unary, coll, valid, cfg.collision_weight,
                                                    cfg.sweeps, order)


def plan_actions(encoder_params, state, cfg: Config, ar: SimplARConfig,
                 controlled: Optional[Array] = None, rng: Optional[Array] = None) -> tuple[Array, Array]:
  """(O, 2) the action tracking each object's chosen mode and (O,) planned mask,
  one scene. controlled (O,): modelled first after the SDC (never dropped for
  a closer newcomer); rng: the mode draw of `ar.sample`."""
  feats = features_lib.scene_features(state, cfg.features, keep=controlled)
  out = encoder.apply(encoder_params, feats, cfg.encoder)
  speed = planner.agent_speed(feats)
  actions = latent.actions_from_positions(out.trajectories, speed[:, None], cfg.kinematics)  # (A,K,T,2)
  states = dynamics.rollout(latent.initial_states(jnp.broadcast_to(speed[:, None], actions.shape[:2])),
                            actions, cfg.kinematics.dt)                      # (A, K, T, 4)
  xy, yaw = features_lib.agent_to_scene(states[..., :ar.lookahead, :2], states[..., :ar.lookahead, 2],
                                        feats)
  length, width = planner.agent_size(feats)
  coll = collision_counts(xy, yaw, length, width, feats.agent_valid)
  modes = select_modes(out.probs, coll, feats.agent_valid, ar, rng)
  chosen = jnp.take_along_axis(out.trajectories, modes[:, None, None, None], 1)[:, 0]  # (A, T, 2)
  action = dynamics.clip_action(tracking_action(chosen, speed, ar, cfg.kinematics.dt), cfg.kinematics)
  num_objects = state.object_metadata.ids.shape[-1]
  per_object = features_lib.scatter_to_objects(action, feats, num_objects)
  planned = features_lib.scatter_to_objects(feats.agent_valid, feats, num_objects, fill=False)
  return per_object, planned.astype(bool)


def simpl_ar(cfg: Config, ar: SimplARConfig = SimplARConfig()) -> Actor:
  """The SIMPL-AR baseline as an Actor; params = the stage-1 encoder parameters.
  The controlled set is fixed at `init` (the policy's reactive set) and
  modelled whole at every step."""
  from pcdiff_jax.policy import reactive_set

  def select_action(params, state, controlled, rng):
    plan, planned = plan_actions(params, state, cfg, ar, controlled, rng)
    valid = controlled & state.current_sim_trajectory.valid[..., 0]
    data = jnp.where((valid & planned)[:, None], plan, 0.0)   # beyond the model's cap: hold (zero action)
    return ActorOutput(actor_state=controlled, action=Action(data=data, valid=valid[:, None]),
                       is_controlled=controlled)

  return Actor(select_action=select_action, init=lambda rng, state: reactive_set(state, cfg),
               name="simpl-ar")
