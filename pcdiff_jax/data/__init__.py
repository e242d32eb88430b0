"""Data: WOMD TFRecords <-> SimulatorState."""
from pcdiff_jax.data import womd
