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
class Config:
  kinematics: KinematicsConfig = KinematicsConfig()
  metrics: MetricsConfig = MetricsConfig()


PRESETS: dict[str, Config] = {
    "tiny": Config(metrics=MetricsConfig(max_reactive_agents=8, max_road_edge_points=512)),
    "cpu": Config(),
    "paper": Config(),
}


def get_config(name: str) -> Config:
  if name not in PRESETS:
    raise ValueError(f"unknown config preset {name!r}; choose one of {sorted(PRESETS)}")
  return PRESETS[name]


def to_dict(config: Any) -> dict:
  return dataclasses.asdict(config)


def to_json(config: Any) -> str:
  return json.dumps(to_dict(config), indent=2, sort_keys=True)
