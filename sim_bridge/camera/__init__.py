"""The emulated camera: what the UAV's camera sees of the AGV, and how the frame reaches the
client.

``camera`` (:class:`Camera`: pose, projection, rendering), ``scene`` (the ground and the
anti-aliased coverage), ``target`` (the AGV box and its top), ``lens`` (pinhole or calibrated
lens, ``read_calibration``), ``sensor`` (timing, photometric noise, motion-blur kernel) and
``frames`` (the TCP frame socket and its wire format, docs/reference/wire.md).
"""

from __future__ import annotations

from sim_bridge.camera.camera import Camera, RenderedFrame
from sim_bridge.camera.lens import Lens, read_calibration
from sim_bridge.camera.scene import SKY_LEVEL
from sim_bridge.camera.sensor import CameraTiming, Capture, Sensor, line_kernel

__all__ = ["SKY_LEVEL", "Camera", "CameraTiming", "Capture", "Lens", "RenderedFrame", "Sensor",
           "line_kernel", "read_calibration"]
