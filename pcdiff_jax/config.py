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
  max_road_edge_points: int = 4096  # nearest road-edge samples kept for off-road checks


@dataclasses.dataclass(frozen=True)
class FeaturesConfig:
  """Fixed padded sizes of the scene instances (`pcdiff_jax.model.features`).

  Agents: up to `max_agents` objects valid at the replanning step, the SDC
  first, then nearest the SDC; `history_steps` steps ending at that step.
  Map: polylines cut into pieces of at most `segment_length` metres (equal
  pieces per polyline), each resampled to `points_per_polyline` points; the
  `max_polylines` pieces nearest the SDC are kept.
  """
  max_agents: int = 64
  history_steps: int = 11
  max_polylines: int = 256
  points_per_polyline: int = 10
  segment_length: float = 20.0     # m


@dataclasses.dataclass(frozen=True)
class EncoderConfig:
  """The SIMPL-style scene encoder (`pcdiff_jax.model.encoder`).

  `num_neighbors`: edges per token (its k nearest tokens, itself included);
  0 means all pairs. `radius` scales distances in the relative pose encoding.
  Proposals: `num_modes` Bezier curves of degree `bezier_degree` over
  `horizon` steps.
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


@dataclasses.dataclass(frozen=True)
class Config:
  kinematics: KinematicsConfig = KinematicsConfig()
  metrics: MetricsConfig = MetricsConfig()
  features: FeaturesConfig = FeaturesConfig()
  encoder: EncoderConfig = EncoderConfig()


PRESETS: dict[str, Config] = {
    "tiny": Config(
        metrics=MetricsConfig(max_reactive_agents=8, max_road_edge_points=512),
        features=FeaturesConfig(max_agents=8, history_steps=11, max_polylines=32,
                                points_per_polyline=8, segment_length=20.0),
        encoder=EncoderConfig(d_model=32, num_heads=4, num_layers=2, agent_blocks=1,
                              num_neighbors=16, dropout=0.0, bezier_degree=5)),
    "cpu": Config(
        features=FeaturesConfig(max_agents=64, history_steps=11, max_polylines=256,
                                points_per_polyline=10, segment_length=20.0),
        encoder=EncoderConfig(d_model=64, num_heads=4, num_layers=2, agent_blocks=2,
                              num_neighbors=32, dropout=0.1, bezier_degree=7)),
    "paper": Config(
        features=FeaturesConfig(max_agents=64, history_steps=11, max_polylines=256,
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


def to_json(config: Any) -> str:
  return json.dumps(to_dict(config), indent=2, sort_keys=True)
