"""Baseline actors (Waymax actor contract)."""
from pcdiff_jax.baselines.simple import constant_velocity, expert, log_replay, reactive_agents, waymax_actor
from pcdiff_jax.baselines.route import IDMRouteConfig, idm_route
