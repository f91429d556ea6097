"""The cloud's memory of each robot's sensors (``AgentSensors`` from the edges), by robot name.

Sans-I/O bookkeeping for :class:`~services.cloud.app.CloudApp`: which camera each robot has
(every atlas agent of that robot projects with it: ``MapFusion.cameras``), and the feature
codec its keyframes were coded with (its image size, as the edge re-codes them). The app
persists what :meth:`RobotSensorBook.learn` returns in the same transaction as the message's
delivered position. A robot whose sensors never arrived (recordings made before calibrations
travelled) falls back to the service's camera.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

from common.calibration import CameraCalibration
from common.codec import CodecConfig
from common.links.edge_cloud import AgentSensors, read_agent_sensors
from common.links.sensors import Sensors, decode_sensors, encode_sensors

log = logging.getLogger(__name__)


class RobotSensorBook:
    """Robot name -> :class:`~common.links.sensors.Sensors`; ``stored``: the encoded
    descriptions a previous run persisted (``CloudStore.sensors()``)."""

    def __init__(self, stored: Mapping[str, bytes], fallback: CameraCalibration | None) -> None:
        self.fallback = fallback
        self.sensors: dict[str, Sensors] = {
            name: decode_sensors(blob, f"stored sensors of {name!r}")
            for name, blob in stored.items()
        }

    def camera(self, name: str) -> CameraCalibration | None:
        """Robot ``name``'s own camera (None: not received)."""
        s = self.sensors.get(name)
        return None if s is None else s.camera

    def codec(self, name: str) -> CodecConfig:
        """The feature codec of robot ``name``'s keyframes (the fallback camera's image size
        for a robot whose sensors never arrived)."""
        cam = self.camera(name) or self.fallback
        if cam is None:
            return CodecConfig()
        return CodecConfig(image_width=cam.width, image_height=cam.height)

    def learn(self, edge_id: str, msg: AgentSensors) -> tuple[str, bytes] | None:
        """Take in ``msg`` (SensorsDecodeError if it does not decode): ``(robot name, encoded
        sensors)`` to persist when they are new; None for a repeat. A robot that comes back
        with other sensors keeps its first ones (logged as an error; its edge refuses such a
        re-join, so only an edge restarted without its journal can send it)."""
        new = read_agent_sensors(msg)
        name = msg.agent_id
        old = self.sensors.get(name)
        if old is not None:
            if not old.same_as(new):
                log.error(
                    "edge %s: robot %r described other sensors (%s) than it has here (%s); "
                    "keeping the first",
                    edge_id,
                    name,
                    new.summary(),
                    old.summary(),
                )
            return None
        self.sensors[name] = new
        log.info("robot %r (edge %s): %s", name, edge_id, new.summary())
        return name, encode_sensors(new)
