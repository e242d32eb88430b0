"""Frozen configs, nested by concept, with named presets.

Pass a function the smallest sub-config it needs. Presets: `tiny` (tests),
`cpu` (the demo on a 2-core machine), `paper` (the published sizes).
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any


@dataclasses.dataclass(frozen=True)
class KinematicsConfig:
  """The paper's kinematic model f: state [x, y, psi, v], action [a, psi_dot].

  Bounds apply to the inverse (and clip the forward model's inputs); the
  heading is held below `min_speed_for_heading`, where the direction of a
  few-centimetre displacement is noise.
  """
  dt: float = 0.1
  max_accel: float = 10.0          # m/s^2
  max_yaw_rate: float = 2.0        # rad/s
  min_speed_for_heading: float = 0.6  # m/s, as Waymax's bicycle inverse


@dataclasses.dataclass(frozen=True)
class MetricsConfig:
  """Which agents are evaluated and how events are counted."""
  max_reactive_agents: int = 64    # nearest the SDC, SDC excluded from evaluation
  max_road_edge_points: int = 512   # road-edge samples searched per object and second (`offroad`)


@dataclasses.dataclass(frozen=True)
class FeaturesConfig:
  """Fixed padded sizes of the scene instances (`pcdiff_jax.model.features`).

  Agents: up to `max_agents` objects valid at the replanning step, the SDC
  first, then nearest the SDC; `history_steps` steps ending at that step.
  Map: polylines cut into pieces of at most `segment_length` metres (equal
  pieces per polyline), each resampled to `points_per_polyline` points; the
  `max_polylines` pieces nearest the SDC are kept (`map_anchor="agents"`:
  nearest any modelled agent). Training crops on the SDC; a trained model
  runs on `RUN_MAP_ANCHOR` (`pretrained()`, `EvalConfig`).
  """
  max_agents: int = 65             # the SDC + the 64 reactive agents scored by MetricsConfig
  history_steps: int = 11
  max_polylines: int = 256
  points_per_polyline: int = 10
  segment_length: float = 20.0     # m
  map_anchor: str = "sdc"


# The map crop a trained model runs with: the pieces nearest any modelled agent, so an agent far
# from the SDC keeps the map around it (docs/RESULTS.md, "Ablation: the model's map anchored on
# the agents").
RUN_MAP_ANCHOR = "agents"


@dataclasses.dataclass(frozen=True)
class EncoderConfig:
  """The SIMPL-style scene encoder (`pcdiff_jax.model.encoder`).

  `num_neighbors`: edges per token (its k nearest tokens, itself included);
  0 means all pairs. `radius` scales distances in the relative pose encoding.
  Proposals: `num_modes` Bezier curves of degree `bezier_degree` over
  `horizon` steps. `anchor_velocity`: the second control point is fixed so
  each curve starts at the agent's current forward velocity (SIMPL pins only
  the start position; a free start velocity puts a jump into every
  proposal's first action, which the closed loop executes at 10 Hz).
  `lane_inputs` adds each agent's lane-relative inputs (`model.lane_context`)
  to its token and to the proposal head through zero-initialised projections
  (`encoder.with_new_inputs`: a model trained without them loads unchanged).
  """
  d_model: int = 128
  num_heads: int = 8
  num_layers: int = 4
  ffn_multiplier: int = 2
  agent_blocks: int = 2            # residual 1-D conv blocks of the agent net
  num_neighbors: int = 64
  radius: float = 100.0            # m
  dropout: float = 0.1
  num_modes: int = 6
  horizon: int = 80                # steps at 10 Hz
  bezier_degree: int = 7
  proposal_scale: float = 10.0     # m, output scale of the control points
  anchor_velocity: bool = True
  lane_inputs: bool = False        # each agent's lane-relative inputs (`model.lane_context`)


@dataclasses.dataclass(frozen=True)
class DenoiserConfig:
  """The joint Transformer denoiser (`pcdiff_jax.model.denoiser`).

  `use_prior` False is the context-only ablation (no proposal tokens).
  `latent_scale` divides latents at the input (and multiplies the output):
  PCA coordinates of standardised actions are a few units. `lane_inputs`
  adds each agent's lane-relative inputs (`model.lane_context`) to its token
  through a zero-initialised projection, so a model trained without them
  loads and starts from the same function (`denoiser.with_new_inputs`).
  `anchor_inputs` conditions each agent on one of its proposals (the
  anchor, added the same way): trained on the proposal nearest the logged
  future, sampled from the proposal probabilities at test time, so a plan
  commits to a mode instead of the mean of stop and go (`planner.draw_anchor`;
  docs/RESULTS.md, "Ablation: anchor inputs").
  """
  d_model: int = 128
  num_heads: int = 8
  num_layers: int = 4
  dropout: float = 0.3
  use_prior: bool = True
  latent_scale: float = 4.0
  radius: float = 100.0            # m, distance scale of the relative pose
  compute_dtype: str = "float32"   # or "bfloat16" (matmuls; parameters stay float32)
  lane_inputs: bool = False        # each agent's lane-relative inputs (`model.lane_context`)
  anchor_inputs: bool = False      # each agent's anchor proposal (`planner.draw_anchor`)


@dataclasses.dataclass(frozen=True)
class DiffusionConfig:
  """Latent, schedule, sampler and stage-2 loss (`model.latent`, `model.diffusion`).

  Without the prior (`denoiser.use_prior` False) sampling starts from N(0, I)
  and the noise is unscaled (sigma = 1).
  """
  latent_dim: int = 32
  num_steps: int = 100
  beta_min: float = 1e-4
  beta_max: float = 5e-2
  eps_sigma: float = 0.3           # added to the proposal spread (OptTrajDiff's regulariser)
  # How mu and sigma come from the K proposals: "uniform" (the paper's mean and std over the
  # modes) or "weighted" (weighted by the encoder's probabilities: an agent whose encoder is sure
  # gets a narrow prior around its likely mode, `diffusion.prior_from_proposals`).
  prior_spread: str = "uniform"
  ddim_steps: int = 5
  eta: float = 0.0
  diffusion_loss_weight: float = 1.0
  state_loss_weight: float = 0.5
  pca_fit_scenes: int = 500        # training scenes whose futures fit the PCA
  pca_proposal_weight: float = 0.0  # share of the proposals in the PCA fit (models v2: 0.5)
  # Stage-2 targets: 0 takes the projection of the inverse actions; sigma > 0 (m) the latent
  # fitted to the future's positions with that tolerance (`latent.fit_to_path`; real logs).
  target_fit_sigma: float = 0.0
  # With a fit: an agent whose fitted latent has a whitened RMS above this is not trained on
  # (a box heading unrelated to the motion makes a path the latent cannot hold); 0: no limit.
  target_max_rms: float = 0.0
  denoiser: DenoiserConfig = DenoiserConfig()


@dataclasses.dataclass(frozen=True)
class PerturbConfig:
  """Recovery examples (`training.perturb`): with probability `prob`, a moving
  vehicle is displaced by up to `max_lateral` m sideways and `max_heading` rad
  at the current step, and its target re-joins the log within
  `rejoin_seconds`. prob 0 turns it off."""
  prob: float = 0.0
  max_lateral: float = 1.5         # m
  max_heading: float = 0.15        # rad
  rejoin_seconds: float = 3.0
  min_speed: float = 2.0           # m/s


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """One training stage (`pcdiff_jax.training.trainer`).

  AdamW with a linear warm-up to `learning_rate` over `warmup_steps`, then a
  cosine decay to `final_lr_fraction` x it at `total_steps`; gradients are
  clipped to a global norm of `grad_clip`. Every `*_every` counts optimizer
  steps. Examples are the scenes at the replanning steps `current_steps`;
  `perturb` adds recovery examples to the training batches (not validation),
  `history_dropout` hides histories in an encoder stage's batches.
  """
  batch_size: int = 16
  learning_rate: float = 1e-3
  final_lr_fraction: float = 0.05
  weight_decay: float = 1e-2
  warmup_steps: int = 200
  total_steps: int = 20000
  grad_clip: float = 1.0
  cls_weight: float = 1.0
  eval_batch_size: int = 16
  log_every: int = 20
  eval_every: int = 1000
  checkpoint_every: int = 200
  keep_checkpoints: int = 2
  seed: int = 0
  current_steps: tuple[int, ...] = (10,)
  perturb: PerturbConfig = PerturbConfig()
  # Encoder stages only: with this probability an agent's history before the
  # current step is hidden (`perturb.drop_history`), so the proposals learn to
  # read the scene, not to extrapolate a history the policy itself drove.
  history_dropout: float = 0.0


@dataclasses.dataclass(frozen=True)
class Config:
  kinematics: KinematicsConfig = KinematicsConfig()
  metrics: MetricsConfig = MetricsConfig()
  features: FeaturesConfig = FeaturesConfig()
  encoder: EncoderConfig = EncoderConfig()
  encoder_train: TrainConfig = TrainConfig()
  diffusion: DiffusionConfig = DiffusionConfig()
  diffusion_train: TrainConfig = TrainConfig(learning_rate=5e-4, weight_decay=1e-3)


_CPU_ENCODER = EncoderConfig(d_model=64, num_heads=4, num_layers=2, agent_blocks=2,
                             num_neighbors=32, dropout=0.1, bezier_degree=7)
_CPU_DENOISER = DenoiserConfig(d_model=64, num_heads=4, num_layers=2, dropout=0.1)
_RECOVERY = PerturbConfig(prob=0.5)

PRESETS: dict[str, Config] = {
    "tiny": Config(
        metrics=MetricsConfig(max_reactive_agents=8, max_road_edge_points=512),
        features=FeaturesConfig(max_agents=9, history_steps=11, max_polylines=32,
                                points_per_polyline=8, segment_length=20.0),
        encoder=EncoderConfig(d_model=32, num_heads=4, num_layers=2, agent_blocks=1,
                              num_neighbors=16, dropout=0.0, bezier_degree=5),
        encoder_train=TrainConfig(batch_size=2, warmup_steps=2, total_steps=6, eval_batch_size=2,
                                  log_every=1, eval_every=3, checkpoint_every=2,
                                  perturb=PerturbConfig(prob=0.5)),
        diffusion=DiffusionConfig(latent_dim=8, pca_fit_scenes=8, denoiser=DenoiserConfig(
            d_model=32, num_heads=4, num_layers=1, dropout=0.0)),
        diffusion_train=TrainConfig(batch_size=2, learning_rate=5e-4, weight_decay=1e-3,
                                    warmup_steps=2, total_steps=6, eval_batch_size=2,
                                    log_every=1, eval_every=3, checkpoint_every=2,
                                    perturb=PerturbConfig(prob=0.5))),
    # The shipped models' preset (CHANGELOG.md, v3 on): recovery examples in both stages,
    # latent fitted on futures only, longer schedules for the 10k-scene set.
    "cpu": Config(
        features=FeaturesConfig(max_agents=65, history_steps=11, max_polylines=256,
                                points_per_polyline=10, segment_length=20.0),
        encoder=_CPU_ENCODER,
        encoder_train=TrainConfig(batch_size=8, learning_rate=2e-3, warmup_steps=100,
                                  total_steps=2500, eval_every=500, checkpoint_every=100,
                                  current_steps=(10, 30), perturb=_RECOVERY),
        diffusion=DiffusionConfig(denoiser=_CPU_DENOISER),
        diffusion_train=TrainConfig(batch_size=8, learning_rate=5e-4, weight_decay=1e-3,
                                    warmup_steps=100, total_steps=2000, eval_every=500,
                                    checkpoint_every=100, perturb=_RECOVERY)),
    # `make demo`: the whole pipeline in minutes on 2 cores (cpu-sized layers,
    # half the agents and map pieces, a few hundred steps per stage).
    "demo": Config(
        metrics=MetricsConfig(max_reactive_agents=32, max_road_edge_points=2048),
        features=FeaturesConfig(max_agents=33, history_steps=11, max_polylines=128,
                                points_per_polyline=10, segment_length=20.0),
        encoder=_CPU_ENCODER,
        encoder_train=TrainConfig(batch_size=8, learning_rate=2e-3, warmup_steps=50,
                                  total_steps=400, eval_every=400, checkpoint_every=100,
                                  current_steps=(10, 30)),
        diffusion=DiffusionConfig(pca_fit_scenes=200, denoiser=_CPU_DENOISER),
        diffusion_train=TrainConfig(batch_size=8, learning_rate=1e-3, weight_decay=1e-3,
                                    warmup_steps=50, total_steps=400, eval_every=400,
                                    checkpoint_every=100)),
    "paper": Config(
        features=FeaturesConfig(max_agents=65, history_steps=11, max_polylines=256,
                                points_per_polyline=10, segment_length=20.0),
        encoder=EncoderConfig(d_model=128, num_heads=8, num_layers=4, agent_blocks=2,
                              num_neighbors=64, dropout=0.1, bezier_degree=7)),
}


def get_config(name: str) -> Config:
  if name not in PRESETS:
    raise ValueError(f"unknown config preset {name!r}; choose one of {sorted(PRESETS)}")
  return PRESETS[name]


def to_dict(config: Any) -> dict:
  return dataclasses.asdict(config)


def _build(cls, value):
  if dataclasses.is_dataclass(cls):
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = set(value) - set(known)
    if unknown:
      raise ValueError(f"unknown {cls.__name__} fields {sorted(unknown)}")
    kwargs = {}
    for name, v in value.items():
      default = getattr(cls(), name)
      kwargs[name] = (_build(type(default), v) if dataclasses.is_dataclass(default)
                      else tuple(v) if isinstance(default, tuple) else v)
    return cls(**kwargs)
  return value


def from_dict(value: dict) -> Config:
  """Inverse of `to_dict` (e.g. the config saved with a checkpoint)."""
  return _build(Config, value)


def to_json(config: Any) -> str:
  return json.dumps(to_dict(config), indent=2, sort_keys=True)
