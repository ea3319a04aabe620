"""The control loop: one step per camera frame, from pixels to the attitude setpoint.

- :mod:`~companion.control.seams`: the typed seams (frame source, perceiver, controller)
- :mod:`~companion.control.telemetry`: the telemetry store (attitude history, kinematics, target)
- :mod:`~companion.control.pipeline`: ``ControlPipeline.step`` (no I/O, no clock: replay-exact)
- :mod:`~companion.control.safety`: the safety ladder (tracking -> terminal -> hover -> ...)
- :mod:`~companion.control.offboard`: PX4 offboard engagement (proof of life, mode, hand-back)
- :mod:`~companion.control.runtime`: the asyncio process wiring camera, link, pipeline and log
"""
