"""Our policy inside a Waymax environment loop, on Waymax's own dataloader.

  pip install git+https://github.com/waymo-research/waymax   # not on the package registry
  python examples/waymax_loop.py --record ../shared/data/womd/motion_data_one_example.tfrecord \
      --dynamics bicycle --steps 80

Waymax's `MultiAgentEnvironment` steps every object valid at t = 10 with the
chosen dynamics model; our policy (the shipped model) drives the 64 agents
nearest the SDC, Waymax's expert actor every other object (the SDC included)
along its log. `policy.waymax_actor` converts the plan's [a, psi_dot] into the
environment's action space and returns Waymax's own `WaymaxActorOutput` /
`Action`, so `agents.merge_actions` takes it as it is. Prints Waymax's own
overlap / off-road metrics at the end. Exits 2 with a clear message when
Waymax is not installed.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))   # run from a clone


def parse_args(argv=None):
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--record", required=True, help="a WOMD tf.Example TFRecord (e.g. the real sample)")
  p.add_argument("--dynamics", default="bicycle", choices=("bicycle", "delta_local", "delta_global"))
  p.add_argument("--steps", type=int, default=80, help="closed-loop steps after t = 10 (at most 80)")
  p.add_argument("--checkpoint", default=None, help="a shipped model directory (default: pcdiff_jax.pretrained())")
  p.add_argument("--ddim-steps", type=int, default=5)
  return p.parse_args(argv)


def main(argv=None) -> int:
  args = parse_args(argv)
  try:
    from waymax import agents, config as wconfig, dataloader, dynamics as wdynamics, env as wenv
  except ImportError as err:
    print(f"error: waymax is not importable ({err}); install it from its repository: "
          "pip install git+https://github.com/waymo-research/waymax", file=sys.stderr)
    return 2
  import jax
  import jax.numpy as jnp
  import numpy as np
  import pcdiff_jax
  from pcdiff_jax import policy

  models, cfg = pcdiff_jax.pretrained(path=args.checkpoint)
  # Waymax's dataloader on the record. Keep every roadgraph point (WOMD has
  # at most 30000): below the record's size Waymax orders points by distance,
  # and our map features need each polyline's points contiguous.
  data_cfg = dataclasses.replace(wconfig.WOD_1_1_0_VALIDATION, path=args.record, max_num_objects=128,
                                 max_num_rg_points=30000, repeat=None, shuffle_seed=None)
  try:
    scenario = next(dataloader.simulator_state_generator(data_cfg))
  except Exception:  # fewer points than the cap: take the record's own count (no reordering)
    data_cfg = dataclasses.replace(data_cfg, max_num_rg_points=20000)
    scenario = next(dataloader.simulator_state_generator(data_cfg))

  model = {"bicycle": wdynamics.InvertibleBicycleModel(), "delta_local": wdynamics.DeltaLocal(),
           "delta_global": wdynamics.DeltaGlobal()}[args.dynamics]
  env = wenv.MultiAgentEnvironment(
      dynamics_model=model,
      config=dataclasses.replace(wconfig.EnvironmentConfig(), max_num_objects=128,
                                 controlled_object=wconfig.ObjectType.VALID))
  ours = policy.waymax_actor(cfg, policy.PolicyConfig(ddim_steps=args.ddim_steps), model)
  # Waymax's expert (the log's inverse) for every object; ours override it where they control.
  expert = agents.create_expert_actor(dynamics_model=model,
                                      is_controlled_func=lambda s: jnp.ones(s.object_metadata.ids.shape, bool))
  state = env.reset(scenario)
  rng = jax.random.PRNGKey(0)
  actor_state = ours.init(rng, state)

  @jax.jit
  def step(state, actor_state, rng):
    mine = ours.select_action(models, state, actor_state, rng)   # Waymax's WaymaxActorOutput / Action
    log = expert.select_action({}, state, None, None)
    action = agents.merge_actions([log, mine])                   # later outputs win where they control
    return env.step(state, action), mine.actor_state

  steps = min(args.steps, int(state.remaining_timesteps))
  for k in range(steps):
    state, actor_state = step(state, actor_state, jax.random.fold_in(rng, k))
  final = env.metrics(state)
  controlled = np.asarray(actor_state.controlled)
  for name in ("overlap", "offroad"):
    if name in final:
      value = np.asarray(final[name].value)[controlled]
      print(f"{name} (our {controlled.sum()} agents, t = {int(state.timestep)}): {value.mean():.3f}")
  print(f"waymax loop done: {steps} steps with {type(model).__name__}, actor {ours.name}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
