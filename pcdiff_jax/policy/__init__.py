"""The closed-loop policy: encode -> DDIM joint plan -> select -> decode -> execute.

Two ways to use it from a Waymax-compatible loop:

  actor = policy.actor(cfg, PolicyConfig(ddim_steps=5))     # Actor contract
  out = sim.rollout(state, actor, 80, rng, params=models)   # one lax.scan

  action, controlled = policy.step(state, models, cfg, rng)  # one replanning

`models` (`planner.Models`) and `cfg` come from `training.diffusion_stage.load(workdir)`. The
actor controls the reactive agents: the SDC and up to A - 1 agents nearest it, valid at the
start of the rollout, minus the SDC, which follows its log; every other object follows its log.
The controlled set is fixed at `init`, and every plan models it whole (the SDC, every controlled
agent still alive, then the nearest other objects as context), so a controlled agent is never
dropped for a newcomer. Every `replan_every` steps (2 by default: 5 Hz) the actor plans anew; in
between it executes the plan's next action through the filters, which read the current state.
`step` keeps no plan, so it plans at every call.

One module per step of the recipe:
  config      PolicyConfig, its ranges (`validate`) and overrides (`with_overrides`)
  planning    encode -> sample -> decode (`plan_actions` runs them with selection)
  selection   per agent, one of a replan's joint samples
  execution   the filters on the executed action, temporal ensembling
  actors      `actor`, `waymax_actor`, `step`
"""
from pcdiff_jax.policy.actors import PlanState, actor, controlled_or_default, step, waymax_actor
from pcdiff_jax.policy.config import EXECUTE, PolicyConfig, validate, with_overrides
from pcdiff_jax.policy.execution import (FOLLOW_MAX_BRAKE, FOLLOW_MIN_GAP, STOPPED_REVERSE_SPEED,
                                         controlled_action, cruise_floor, ensemble_plans, execute,
                                         executed_accel, follow_bound, hold_at_stop, limit_curvature,
                                         limit_jerk, logged_accel, safe_speed)
from pcdiff_jax.policy.planning import (START_GATE_SPEED, Encoded, WarmStart, advance_plan, decode, encode,
                                        plan_actions, pursuer_of, reactive_set, road_for, sample,
                                        still_agents, stop_plan, warm_centres)
from pcdiff_jax.policy.selection import select, select_sample

__all__ = [
    "EXECUTE", "Encoded", "FOLLOW_MAX_BRAKE", "FOLLOW_MIN_GAP", "PlanState", "PolicyConfig",
    "START_GATE_SPEED", "STOPPED_REVERSE_SPEED", "WarmStart", "actor", "advance_plan",
    "controlled_action", "controlled_or_default", "cruise_floor", "decode", "encode", "ensemble_plans",
    "execute",
    "executed_accel", "follow_bound", "hold_at_stop", "limit_curvature", "limit_jerk", "logged_accel",
    "plan_actions", "pursuer_of", "reactive_set", "road_for", "safe_speed", "sample", "select",
    "select_sample", "step", "still_agents", "stop_plan", "validate", "warm_centres", "waymax_actor",
    "with_overrides",
]
