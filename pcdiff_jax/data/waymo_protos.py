"""The Waymo Open Dataset messages we read and write, without its package.

Built at import time with protobuf's descriptor API from the public schema
(waymo-research/waymo-open-dataset, `src/waymo_open_dataset/protos/`
`scenario.proto`, `map.proto`, `sim_agents_submission.proto`): the same full
names (`waymo.open_dataset.Scenario`, ...), field numbers, types, labels and
packing, so the bytes are those of the official classes. The messages live in
a private descriptor pool: they never clash with the official package if a
user also imports it. Fields we do not need (Scenario's compressed lidar and
camera tokens, 12 and 13) are left out; the parser keeps them as unknown
fields, so nothing is lost on a read-modify-write.

  from pcdiff_jax.data import waymo_protos as pb
  scenario = pb.Scenario.FromString(raw)
  sub = pb.SimAgentsChallengeSubmission(scenario_rollouts=[...], submission_type=pb.SIM_AGENTS_SUBMISSION)
"""
from __future__ import annotations

from google.protobuf import descriptor_pb2, descriptor_pool

try:  # protobuf >= 4.21
  from google.protobuf.message_factory import GetMessageClass as _message_class
except ImportError:  # pragma: no cover - older protobuf
  from google.protobuf import message_factory as _mf
  _message_class = _mf.MessageFactory().GetPrototype

PACKAGE = "waymo.open_dataset"
_F = descriptor_pb2.FieldDescriptorProto
OPTIONAL, REPEATED = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED
_SCALARS = {"double": _F.TYPE_DOUBLE, "float": _F.TYPE_FLOAT, "int32": _F.TYPE_INT32,
            "int64": _F.TYPE_INT64, "bool": _F.TYPE_BOOL, "string": _F.TYPE_STRING}

# Enums: name -> [(value name, number)]. Nested enums are "Message.Enum".
ENUMS = {
    "Track.ObjectType": [("TYPE_UNSET", 0), ("TYPE_VEHICLE", 1), ("TYPE_PEDESTRIAN", 2),
                         ("TYPE_CYCLIST", 3), ("TYPE_OTHER", 4)],
    "RequiredPrediction.DifficultyLevel": [("NONE", 0), ("LEVEL_1", 1), ("LEVEL_2", 2)],
    "TrafficSignalLaneState.State": [
        ("LANE_STATE_UNKNOWN", 0), ("LANE_STATE_ARROW_STOP", 1), ("LANE_STATE_ARROW_CAUTION", 2),
        ("LANE_STATE_ARROW_GO", 3), ("LANE_STATE_STOP", 4), ("LANE_STATE_CAUTION", 5),
        ("LANE_STATE_GO", 6), ("LANE_STATE_FLASHING_STOP", 7), ("LANE_STATE_FLASHING_CAUTION", 8)],
    "LaneCenter.LaneType": [("TYPE_UNDEFINED", 0), ("TYPE_FREEWAY", 1), ("TYPE_SURFACE_STREET", 2),
                            ("TYPE_BIKE_LANE", 3)],
    "RoadEdge.RoadEdgeType": [("TYPE_UNKNOWN", 0), ("TYPE_ROAD_EDGE_BOUNDARY", 1),
                              ("TYPE_ROAD_EDGE_MEDIAN", 2)],
    "RoadLine.RoadLineType": [
        ("TYPE_UNKNOWN", 0), ("TYPE_BROKEN_SINGLE_WHITE", 1), ("TYPE_SOLID_SINGLE_WHITE", 2),
        ("TYPE_SOLID_DOUBLE_WHITE", 3), ("TYPE_BROKEN_SINGLE_YELLOW", 4), ("TYPE_BROKEN_DOUBLE_YELLOW", 5),
        ("TYPE_SOLID_SINGLE_YELLOW", 6), ("TYPE_SOLID_DOUBLE_YELLOW", 7), ("TYPE_PASSING_DOUBLE_YELLOW", 8)],
    "SimAgentsChallengeSubmission.SubmissionType": [("UNKNOWN", 0), ("SIM_AGENTS_SUBMISSION", 1)],
}

# Messages: name -> [(field, number, label, type, packed)], type a scalar name,
# a message or enum name; "oneof:NAME" after the type puts a field in a oneof.
O, R, P = "optional", "repeated", "packed"
MESSAGES = {
    # map.proto
    "MapPoint": [("x", 1, O, "double"), ("y", 2, O, "double"), ("z", 3, O, "double")],
    "TrafficSignalLaneState": [("lane", 1, O, "int64"), ("state", 2, O, "TrafficSignalLaneState.State"),
                               ("stop_point", 3, O, "MapPoint")],
    "BoundarySegment": [("lane_start_index", 1, O, "int32"), ("lane_end_index", 2, O, "int32"),
                        ("boundary_feature_id", 3, O, "int64"),
                        ("boundary_type", 4, O, "RoadLine.RoadLineType")],
    "LaneNeighbor": [("feature_id", 1, O, "int64"), ("self_start_index", 2, O, "int32"),
                     ("self_end_index", 3, O, "int32"), ("neighbor_start_index", 4, O, "int32"),
                     ("neighbor_end_index", 5, O, "int32"), ("boundaries", 6, R, "BoundarySegment")],
    "LaneCenter": [("speed_limit_mph", 1, O, "double"), ("type", 2, O, "LaneCenter.LaneType"),
                   ("interpolating", 3, O, "bool"), ("polyline", 8, R, "MapPoint"),
                   ("entry_lanes", 9, P, "int64"), ("exit_lanes", 10, P, "int64"),
                   ("left_boundaries", 13, R, "BoundarySegment"), ("right_boundaries", 14, R, "BoundarySegment"),
                   ("left_neighbors", 11, R, "LaneNeighbor"), ("right_neighbors", 12, R, "LaneNeighbor")],
    "RoadEdge": [("type", 1, O, "RoadEdge.RoadEdgeType"), ("polyline", 2, R, "MapPoint")],
    "RoadLine": [("type", 1, O, "RoadLine.RoadLineType"), ("polyline", 2, R, "MapPoint")],
    "StopSign": [("lane", 1, R, "int64"), ("position", 2, O, "MapPoint")],
    "Crosswalk": [("polygon", 1, R, "MapPoint")],
    "SpeedBump": [("polygon", 1, R, "MapPoint")],
    "Driveway": [("polygon", 1, R, "MapPoint")],
    "MapFeature": [("id", 1, O, "int64"), ("lane", 3, O, "LaneCenter", "oneof:feature_data"),
                   ("road_line", 4, O, "RoadLine", "oneof:feature_data"),
                   ("road_edge", 5, O, "RoadEdge", "oneof:feature_data"),
                   ("stop_sign", 7, O, "StopSign", "oneof:feature_data"),
                   ("crosswalk", 8, O, "Crosswalk", "oneof:feature_data"),
                   ("speed_bump", 9, O, "SpeedBump", "oneof:feature_data"),
                   ("driveway", 10, O, "Driveway", "oneof:feature_data")],
    # scenario.proto
    "ObjectState": [("center_x", 2, O, "double"), ("center_y", 3, O, "double"), ("center_z", 4, O, "double"),
                    ("length", 5, O, "float"), ("width", 6, O, "float"), ("height", 7, O, "float"),
                    ("heading", 8, O, "float"), ("velocity_x", 9, O, "float"), ("velocity_y", 10, O, "float"),
                    ("valid", 11, O, "bool")],
    "Track": [("id", 1, O, "int32"), ("object_type", 2, O, "Track.ObjectType"), ("states", 3, R, "ObjectState")],
    "DynamicMapState": [("lane_states", 1, R, "TrafficSignalLaneState")],
    "RequiredPrediction": [("track_index", 1, O, "int32"),
                           ("difficulty", 2, O, "RequiredPrediction.DifficultyLevel")],
    "Scenario": [("scenario_id", 5, O, "string"), ("timestamps_seconds", 1, R, "double"),
                 ("current_time_index", 10, O, "int32"), ("tracks", 2, R, "Track"),
                 ("dynamic_map_states", 7, R, "DynamicMapState"), ("map_features", 8, R, "MapFeature"),
                 ("sdc_track_index", 6, O, "int32"), ("objects_of_interest", 4, R, "int32"),
                 ("tracks_to_predict", 11, R, "RequiredPrediction")],
    # sim_agents_submission.proto
    "SimulatedTrajectory": [("center_x", 2, P, "float"), ("center_y", 3, P, "float"),
                            ("center_z", 4, P, "float"), ("heading", 5, P, "float"),
                            ("width", 7, P, "float"), ("length", 8, P, "float"), ("height", 9, P, "float"),
                            ("valid", 11, P, "bool"), ("object_id", 6, O, "int32"),
                            ("object_type", 10, O, "Track.ObjectType")],
    "JointScene": [("simulated_trajectories", 1, R, "SimulatedTrajectory")],
    "ScenarioRollouts": [("scenario_id", 1, O, "string"), ("joint_scenes", 2, R, "JointScene")],
    "SimAgentsChallengeSubmission": [
        ("scenario_rollouts", 1, R, "ScenarioRollouts"),
        ("submission_type", 2, O, "SimAgentsChallengeSubmission.SubmissionType"),
        ("account_name", 3, O, "string"), ("unique_method_name", 4, O, "string"),
        ("authors", 5, R, "string"), ("affiliation", 6, O, "string"), ("description", 7, O, "string"),
        ("method_link", 8, O, "string"), ("uses_lidar_data", 9, O, "bool"), ("uses_camera_data", 10, O, "bool"),
        ("uses_public_model_pretraining", 11, O, "bool"), ("public_model_names", 13, R, "string"),
        ("num_model_parameters", 12, O, "string"),
        ("acknowledge_complies_with_closed_loop_requirement", 14, O, "bool")],
}
RESERVED = {"Scenario": [9]}


def _file_proto() -> descriptor_pb2.FileDescriptorProto:
  f = descriptor_pb2.FileDescriptorProto(name="pcdiff_jax/waymo_open_dataset_subset.proto",
                                         package=PACKAGE, syntax="proto2")
  messages = {name: f.message_type.add(name=name) for name in MESSAGES}
  for full, values in ENUMS.items():
    outer, enum_name = full.split(".")
    enum = messages[outer].enum_type.add(name=enum_name)
    for value_name, number in values:
      enum.value.add(name=value_name, number=number)
  for name, fields in MESSAGES.items():
    msg = messages[name]
    for start in RESERVED.get(name, ()):
      msg.reserved_range.add(start=start, end=start + 1)
    oneofs: dict[str, int] = {}
    for spec in fields:
      field_name, number, label, type_name = spec[:4]
      field = msg.field.add(name=field_name, number=number,
                            label=REPEATED if label in (R, P) else OPTIONAL)
      if type_name in _SCALARS:
        field.type = _SCALARS[type_name]
      else:
        field.type = _F.TYPE_ENUM if type_name in ENUMS else _F.TYPE_MESSAGE
        field.type_name = f".{PACKAGE}.{type_name}"
      if label == P:
        field.options.packed = True
      if len(spec) > 4 and spec[4].startswith("oneof:"):
        oneof = spec[4].split(":", 1)[1]
        if oneof not in oneofs:
          oneofs[oneof] = len(msg.oneof_decl)
          msg.oneof_decl.add(name=oneof)
        field.oneof_index = oneofs[oneof]
  return f


POOL = descriptor_pool.DescriptorPool()
_FILE = POOL.Add(_file_proto())


def _cls(name: str):
  return _message_class(POOL.FindMessageTypeByName(f"{PACKAGE}.{name}"))


MapPoint = _cls("MapPoint")
TrafficSignalLaneState = _cls("TrafficSignalLaneState")
BoundarySegment = _cls("BoundarySegment")
LaneNeighbor = _cls("LaneNeighbor")
LaneCenter = _cls("LaneCenter")
RoadEdge = _cls("RoadEdge")
RoadLine = _cls("RoadLine")
StopSign = _cls("StopSign")
Crosswalk = _cls("Crosswalk")
SpeedBump = _cls("SpeedBump")
Driveway = _cls("Driveway")
MapFeature = _cls("MapFeature")
ObjectState = _cls("ObjectState")
Track = _cls("Track")
DynamicMapState = _cls("DynamicMapState")
RequiredPrediction = _cls("RequiredPrediction")
Scenario = _cls("Scenario")
SimulatedTrajectory = _cls("SimulatedTrajectory")
JointScene = _cls("JointScene")
ScenarioRollouts = _cls("ScenarioRollouts")
SimAgentsChallengeSubmission = _cls("SimAgentsChallengeSubmission")

SIM_AGENTS_SUBMISSION = 1   # SimAgentsChallengeSubmission.SubmissionType
