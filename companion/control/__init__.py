"""The control loop: one step per camera frame, from pixels to the attitude setpoint.

- :mod:`~companion.control.seams`: the typed seams (frame source, perceiver, controller)
- :mod:`~companion.control.telemetry`: the telemetry store (attitude history, kinematics, target)
- :mod:`~companion.control.pipeline`: ``ControlPipeline.step`` (no I/O, no clock: replay-exact)
- :mod:`~companion.control.safety`: the safety ladder (tracking -> terminal -> hover -> ...)
- :mod:`~companion.control.offboard`: PX4 offboard engagement (proof of life, mode, hand-back)
- :mod:`~companion.control.runtime`: the asyncio process wiring camera, link, pipeline and log,
  with its rooms :mod:`~companion.control.vehicle` (the autopilot as the companion sees it:
  store, offboard, TIMESYNC), :mod:`~companion.control.timebase` (one time base for every
  input), :mod:`~companion.control.recording` (what is logged, at which log time),
  :mod:`~companion.control.faults` (fault injection) and :mod:`~companion.control.wiring`
  (what a flight is built from, shared with the replay)
"""
