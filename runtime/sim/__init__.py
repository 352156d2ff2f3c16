"""Paired LiDAR / 4D-radar street simulator writing the View-of-Delft layout.

``msdnet-data simulate --out DIR --sequences N --frames M --seed S [--rig vod|astyx]``.
Modules, in data order: ``trajectory`` (street grid, routes, 10 Hz ego poses), ``scene``
(procedural streets as analytic primitives), ``raycast`` (numba ray caster), ``lidar`` and
``radar`` / ``radar_effects`` (sensor models; the radar model is documented in ``radar``),
``rig`` (mountings and calibration), ``rigs`` (the ``--rig vod|astyx`` vehicles), ``sequence``
(one sequence, frame by frame), ``writer`` (VoD files) and ``command`` (the CLI).
"""

from msdnet.runtime.sim.command import simulate, simulate_dataset
from msdnet.runtime.sim.sequence import SequenceSim

__all__ = ["SequenceSim", "simulate", "simulate_dataset"]
