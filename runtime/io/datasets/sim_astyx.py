"""``--dataset sim-astyx``: a folder simulated with ``msdnet-data simulate --rig astyx``.

The folder is in the VoD layout (read by :class:`VodDataset`); its radar rows are
``x y z mag v_r v_r_compensated time`` with Astyx-like values (``runtime/sim/rigs.py``: the
VoD ``rcs`` column holds the Astyx 6455-like magnitude, ``v_r`` the Astyx-signed, folded radial
speed). This reader renames the columns accordingly, so a model trained on it takes the same
radar columns as on ``--dataset astyx`` (``x y z v_r mag``), and marks the LiDAR as a VLP-16
(the ground-removal preset of the real Astyx frames).
"""

from __future__ import annotations

from dataclasses import replace

from msdnet.runtime.io.datasets.frame import Frame
from msdnet.runtime.io.datasets.vod import VodDataset

# VoD-layout radar row -> Astyx-rig names: column 3 is the magnitude (the rest keep their names)
SIM_ASTYX_RADAR_COLUMNS = ("x", "y", "z", "mag", "v_r", "v_r_compensated", "time")


class SimAstyxDataset(VodDataset):
    """VoD-layout frames of the simulator's Astyx rig; radar columns ``SIM_ASTYX_RADAR_COLUMNS``."""

    def load(self, frame_id: str) -> Frame:
        frame = super().load(frame_id)
        radar = replace(frame.radar, columns=SIM_ASTYX_RADAR_COLUMNS)
        return replace(frame, radar=radar, lidar_rig="vlp16")
