"""Embedded default dataset: procedural traffic scenes in the WOMD tf.Example schema.

`generate_scene(seed, index)` returns one scene as a `SimulatorState` (numpy
leaves) that `pcdiff_jax.data.womd.write` turns into a WOMD record;
`experiments.make_data` shards, parallelises and reports on them.
"""
from pcdiff_jax.data.synthetic.maps import FAMILIES
from pcdiff_jax.data.synthetic.scene import Scene, SyntheticConfig, count_overlaps, generate_scene

__all__ = ["FAMILIES", "Scene", "SyntheticConfig", "count_overlaps", "generate_scene"]
