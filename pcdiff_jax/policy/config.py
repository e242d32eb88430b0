"""PolicyConfig: the closed-loop policy's settings, their ranges and overrides from the command line."""
from __future__ import annotations

import dataclasses

from pcdiff_jax.config import Config
from pcdiff_jax.model import guidance as guidance_lib


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
  """How the policy plans, picks and executes. The defaults are the shipped policy of
  docs/RESULTS.md, "Table I: closed-loop realism and safety (synthetic val200 and test100)";
  CHANGELOG.md says how each default was reached.

  Sampling (docs/RESULTS.md, "Table II: DDIM steps and warm starts"):
    ddim_steps, eta: DDIM steps and stochasticity of a cold plan (the first of a rollout).
    prior_init: start DDIM at the proposal prior; False is the context-only model's N(0, I)
      ("Ablation: the proposal prior").
    prior_centre: "mean" centres the prior on the mean of an agent's K proposal latents, "top1"
      on its most likely one.
    encoder_history: the steps of each agent's history the encoder reads, ending at the
      current one (0: all): 1 for an encoder trained with history dropout, so the policy's
      own past cannot feed its proposals (docs/RESULTS.md, "Ablation: history dropout").
    consistent_noise: draw each object's initial noise once per rollout and reuse it at every
      cold replan, so consecutive plans stay on one mode (smoother, but committed to it).
    guidance: test-time guidance of every plan (`model.guidance`; "Table III: adversarial
      guidance", "Ablation: objective guidance's collision weight").
    pedestrian_plan: "sample" plans pedestrians with the denoiser, as every other agent; "top"
      puts each pedestrian on its likeliest proposal in every sample; "drawn" on its mode in
      sample 0 (the likeliest proposal, or at a warm replan the one nearest its previous plan)
      and on a proposal drawn by probability in each other sample, for the selection to choose;
      "mixed" so in the first half of the samples, the denoiser's in the other half, so a walker
      whose likely proposals all run into a parked car can still be kept off it; "steady" (the
      default) as "mixed" with the walker's speed and heading held in sample 0 (its mode in
      sample 1) where its tracked speed is that of its last second of positions. Guided plans
      keep every agent's guided sample (a proposal would bypass the guidance). On real scenes
      the denoiser's pedestrian samples scatter and leave many walkers standing; on the
      proposals alone they walk, and walk into parked cars, and the likeliest proposal walks
      slower than the walker ("Ablation: pedestrians on their proposals", "Ablation: a walker's
      steady plan").
    pedestrian_steady_travel: with "steady", > 0 also keeps a walker on its mode where the mode
      travels less than this share of the steady plan's distance (a walker stopping at a kerb).
    cyclist_plan: the same choices for cyclists; "steady" (the default) puts a cyclist's steady
      plan in sample 0: the denoiser's and the proposals' cyclists brake and trail constant
      velocity ("Ablation: a cyclist's steady plan").

  Replanning:
    replan_every: simulator steps between plans (2: a plan at 5 Hz, its first two actions
      executed, every step through the filters below; it re-draws half as often as 1 (10 Hz) and
      leaves the road less on real and synthetic scenes: docs/RESULTS.md, "Ablation: how often
      ours replans, and how much each replan keeps"). WOSAC admits up to 10 (1 Hz).
    warm_start: a replan starts from the previous plan, advanced by the executed steps, instead
      of the prior: better realism and minADE at a fifth less time than cold plans (Table II).
    warm_step, warm_ddim_steps: the previous plan is noised to diffusion step warm_step (90: it
      keeps weight sqrt(abar_90) = 0.36, so most of the plan is re-drawn from the current scene)
      and denoised in warm_ddim_steps steps.
    anchor_tau: with a denoiser that reads anchors (`DenoiserConfig.anchor_inputs`), a warm
      replan draws each agent's anchor from p_k exp(-|previous - y_k|^2 / 2 tau^2) over its
      proposals y_k (latent units), so it keeps the mode of its previous plan; 0: the nearest.
      A cold plan draws it with probability p_k^(1 / anchor_temperature) (0: the most likely).
      ("Ablation: anchor inputs"; the shipped model has no anchors, so both are inert.)
    temporal_ensemble: (m_accel, m_yaw_rate): the executed plan is m x the previous plans +
      (1 - m) x the new one per action channel (ACT's temporal ensembling), which averages away
      the sampling noise between consecutive plans; 0 turns a channel off.

  Sample selection ("Ablation: samples per replan"):
    select_samples: S joint samples per replan; each agent keeps the one that overlaps least
      with the others' chosen samples (iterated conditional modes, `model.joint_selection`).
    select_lookahead, select_stride: overlaps are scored over the first select_lookahead
      steps, at every select_stride-th step.
    select_neighbours: overlaps against each agent's N nearest agents only (0: every pair);
      the choice equals the dense one where the (N+1)-th agent cannot reach the samples.
    select_map_weight: weight of each sample's J_map (`guidance.map_cost`, m^2) beside its
      overlaps, so an agent also prefers a sample that stays on the road; 0 turns it off.
    select_map_spare: (probability, metres): a sample is charged only the J_map beyond the
      largest of the agent's own proposals of at least this probability that take a box
      corner at least this far past the road edge, so where the encoder expects a car to
      leave the mapped road (into a lot or driveway the map does not hold) its samples may
      follow it; a proposal that only clips a curb spares nothing. (0, 0) charges every
      excursion (docs/RESULTS.md, "Ablation: the map spare").
    select_held_still: score the agents the still gate holds where they will be (standing at
      their start) rather than where their samples go, so the others' choices avoid the place
      they stand ("Ablation: held agents in the sample selection": fewer collisions on real
      and synthetic scenes, the other rates level).
    select_boxes: overlaps also count one per step where two samples' boxes overlap, so a
      turning box's corner, which the width / 2 circles miss, is seen ("Ablation: box overlaps
      in the sample selection": fewer collisions on real and synthetic scenes, its cost within
      the benchmark's noise).

  Execution (filters on the executed action, `policy.execution`):
    execute: "actions" executes the plan's actions open loop; "track" steers towards the plan's
      point track_steps ahead (pure pursuit, as SIMPL-AR executes its proposals).
    jerk_limit: (rise, fall) m/s^3: the executed acceleration moves from the last executed one
      by at most rise * dt up and fall * dt down; 0 turns a side off.
    jerk_start_bound: m/s^2: before the first executed step the reference is the log's trend
      over its last second within +-this bound (`execution.logged_accel`). A wrong negative
      reference costs a^2 / (2 rise) of speed before the agent may speed up (5.3 m/s at 4,
      1.3 at 2); 2 is the bound nearest the next second's trend on real val's logs
      (docs/RESULTS.md, "Ablation: the jerk limit's first reference").
    follow: (reaction s, braking m/s^2): a vehicle or cyclist accelerates at most as much as
      keeps it able to stop behind every leader on its planned path if both brake this hard,
      reacting this late (Gipps' safe speed, `execution.follow_bound`); (0, 0) is off. Fewer
      rear-end collisions on real and synthetic scenes, the other rates level
      (docs/RESULTS.md, "Ablation: the follow bound").
    follow_crossing: the follow bound also stops a follower before a moving object crossing its
      path where its plan would run into the object's side, constant velocity taking the
      object on (`execution.crossing_gaps`; "Ablation: crossing objects in the follow bound":
      fewer collisions on real and synthetic scenes, the other rates level).
    rear_guard: a vehicle or cyclist accelerates at least as much as keeps it ahead of an object
      closing on it from behind that replays its log (the SDC, objects beyond the reactive set)
      and so will not brake for it, up to 2 m/s^2, and so does a queue of ours ahead of it; the
      follow bound still caps it (`execution.rear_guard`; "Ablation: the rear guard": fewer
      collisions on real val and on the synthetic splits).
    cruise_hold: (m/s, m/s^2): a vehicle at least this fast, on a plan that keeps straight, with
      nothing on its path the follow bound would brake for, brakes at most this hard
      (`execution.cruise_floor`): at highway speeds the plans brake where real drivers keep
      their speed ("Ablation: the cruise hold": less minADE on real val and train, the rates
      level); (0, 0) is off.
    stop_hold: braking ends at standstill, so a stopped car never reverses on plan noise.
    still_gate: (seconds, metres): an agent slower than START_GATE_SPEED whose proposals,
      weighted by probability, carry it less than `metres` within `seconds` is stopped and held
      (parked cars stay parked; a car queued at a green light is let go); (0, 0) is off.
    max_curvature: 1/m: a vehicle or cyclist turns at most this much per metre travelled, so
      a parked car does not spin in place; 0 is off. Both chosen on the real val scenes
      (docs/RESULTS.md, "Table I (real WOMD val)"; CHANGELOG.md, v8 real-traffic defaults).

  Options that were measured without gain are gone; CHANGELOG.md keeps their results.
  """
  ddim_steps: int = 5
  eta: float = 0.0
  prior_init: bool = True
  replan_every: int = 2
  guidance: guidance_lib.GuidanceConfig = guidance_lib.GuidanceConfig()
  consistent_noise: bool = False
  execute: str = "actions"
  track_steps: int = 5
  prior_centre: str = "mean"
  encoder_history: int = 0
  warm_start: bool = True
  warm_step: int = 90
  warm_ddim_steps: int = 1
  anchor_tau: float = 0.0
  anchor_temperature: float = 1.0
  temporal_ensemble: tuple[float, float] = (0.7, 0.0)
  select_samples: int = 8
  select_lookahead: int = 30
  select_map_weight: float = 30.0
  select_map_spare: tuple[float, float] = (0.1, 1.5)
  select_stride: int = 3
  select_neighbours: int = 16
  jerk_limit: tuple[float, float] = (1.5, 5.0)
  jerk_start_bound: float = 2.0
  follow: tuple[float, float] = (0.5, 4.0)
  stop_hold: bool = True
  max_curvature: float = 0.3
  still_gate: tuple[float, float] = (2.0, 1.0)
  select_held_still: bool = True
  select_boxes: bool = True
  follow_crossing: bool = True
  rear_guard: bool = True
  cruise_hold: tuple[float, float] = (15.0, 1.0)
  pedestrian_plan: str = "steady"
  pedestrian_steady_travel: float = 0.0
  cyclist_plan: str = "steady"


EXECUTE = ("actions", "track")
PROPOSAL_PLANS = ("sample", "top", "drawn", "mixed", "steady")   # pedestrian_plan, cyclist_plan


def with_overrides(policy: PolicyConfig, overrides) -> PolicyConfig:
  """`policy` with fields replaced by (name, value) pairs, each value converted
  to the field's type (tuples element-wise); an unknown name is a ValueError
  that lists the fields."""
  fields = {f.name: f for f in dataclasses.fields(PolicyConfig)}
  changes = {}
  for name, value in overrides:
    if name not in fields or name == "guidance":
      raise ValueError(f"unknown policy field {name!r}; choose from {sorted(set(fields) - {'guidance'})}")
    default = getattr(PolicyConfig(), name)
    if isinstance(default, tuple):
      value = tuple(type(d)(v) for d, v in zip(default, value))
    elif isinstance(default, bool):
      value = value if isinstance(value, bool) else str(value).lower() in ("1", "true", "yes", "on")
    else:
      value = type(default)(value)
    changes[name] = value
  return dataclasses.replace(policy, **changes)


def validate(cfg: Config, policy: PolicyConfig) -> None:
  """Raises ValueError naming the first PolicyConfig field out of range."""
  if policy.ddim_steps < 1:
    raise ValueError(f"ddim_steps must be >= 1, got {policy.ddim_steps}")
  if policy.replan_every < 1 or policy.replan_every > cfg.encoder.horizon:
    raise ValueError(f"replan_every must be in [1, {cfg.encoder.horizon}], got {policy.replan_every}")
  if policy.prior_centre not in ("mean", "top1"):
    raise ValueError(f"prior_centre must be 'mean' or 'top1', got {policy.prior_centre!r}")
  if policy.execute not in EXECUTE:
    raise ValueError(f"execute must be one of {EXECUTE}, got {policy.execute!r}")
  if policy.pedestrian_plan not in PROPOSAL_PLANS:
    raise ValueError(f"pedestrian_plan must be one of {PROPOSAL_PLANS}, got {policy.pedestrian_plan!r}")
  if policy.cyclist_plan not in PROPOSAL_PLANS:
    raise ValueError(f"cyclist_plan must be one of {PROPOSAL_PLANS}, got {policy.cyclist_plan!r}")
  if not 0.0 <= policy.pedestrian_steady_travel <= 1.0:
    raise ValueError(f"pedestrian_steady_travel must be in [0, 1], got {policy.pedestrian_steady_travel}")
  if not 2 <= policy.track_steps <= cfg.encoder.horizon:
    raise ValueError(f"track_steps must be in [2, {cfg.encoder.horizon}], got {policy.track_steps}")
  if not 0 <= policy.warm_step < cfg.diffusion.num_steps:
    raise ValueError(f"warm_step must be in [0, {cfg.diffusion.num_steps - 1}], got {policy.warm_step}")
  if len(policy.temporal_ensemble) != 2 or not all(0.0 <= m < 1.0 for m in policy.temporal_ensemble):
    raise ValueError(f"temporal_ensemble must be two weights in [0, 1) (acceleration, yaw rate), "
                     f"got {policy.temporal_ensemble}")
  if not 1 <= policy.warm_ddim_steps <= policy.warm_step + 1:
    raise ValueError(f"warm_ddim_steps must be in [1, warm_step + 1 = {policy.warm_step + 1}], "
                     f"got {policy.warm_ddim_steps}")
  if policy.anchor_tau < 0 or policy.anchor_temperature < 0:
    raise ValueError(f"anchor_tau and anchor_temperature must be >= 0, got {policy.anchor_tau}, "
                     f"{policy.anchor_temperature}")
  if not 1 <= policy.select_samples <= 64:
    raise ValueError(f"select_samples must be in [1, 64], got {policy.select_samples}")
  if not 1 <= policy.select_lookahead <= cfg.encoder.horizon:
    raise ValueError(f"select_lookahead must be in [1, {cfg.encoder.horizon}], got {policy.select_lookahead}")
  if len(policy.jerk_limit) != 2 or not all(j >= 0 for j in policy.jerk_limit):
    raise ValueError(f"jerk_limit must be two limits >= 0 in m/s^3 (rise, fall), got {policy.jerk_limit}")
  if policy.jerk_start_bound < 0:
    raise ValueError(f"jerk_start_bound must be >= 0 m/s^2, got {policy.jerk_start_bound}")
  if not 1 <= policy.select_stride <= policy.select_lookahead:
    raise ValueError(f"select_stride must be in [1, select_lookahead], got {policy.select_stride}")
  if policy.select_neighbours < 0:
    raise ValueError(f"select_neighbours must be >= 0 (0: every pair), got {policy.select_neighbours}")
  if policy.select_map_weight < 0:
    raise ValueError(f"select_map_weight must be >= 0, got {policy.select_map_weight}")
  if (len(policy.select_map_spare) != 2 or not 0 <= policy.select_map_spare[0] <= 1
      or policy.select_map_spare[1] < 0):
    raise ValueError("select_map_spare must be (probability in [0, 1], metres >= 0), or (0, 0) "
                     f"for off; got {policy.select_map_spare}")
  if len(policy.still_gate) != 2 or not all(g >= 0 for g in policy.still_gate):
    raise ValueError(f"still_gate must be (seconds, metres) >= 0, got {policy.still_gate}")
  if len(policy.follow) != 2 or not (all(f > 0 for f in policy.follow) or not any(policy.follow)):
    raise ValueError(f"follow must be (reaction s, braking m/s^2), both > 0, or (0, 0) for off; got {policy.follow}")
  if len(policy.cruise_hold) != 2 or not all(h >= 0 for h in policy.cruise_hold):
    raise ValueError(f"cruise_hold must be (m/s, m/s^2) >= 0, or (0, 0) for off; got {policy.cruise_hold}")
  if policy.max_curvature < 0:
    raise ValueError(f"max_curvature must be >= 0 (1/m; 0: off), got {policy.max_curvature}")
  policy.guidance.validate()
