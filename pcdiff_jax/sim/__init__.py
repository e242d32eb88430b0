"""Waymax-compatible functional simulator: datatypes, dynamics, env, metrics."""
from pcdiff_jax.sim import action_spaces, actors, dynamics, env, geometry, metrics, selection, waymax_interop
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import (Action, ObjectMetadata, ObjectType, RoadgraphPoints,
                                      RoadgraphType, SimulatorState, TrafficLights,
                                      TrafficLightState, Trajectory)
from pcdiff_jax.sim.env import reset, rollout, step
