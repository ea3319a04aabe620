"""The emulator's two clocks, the loops that drive :class:`sim_bridge.app.SimBridge`.

* ``realtime``: boot time follows the wall clock (``time.monotonic``); the physics is integrated
  in fixed steps up to "now" every tick; setpoints are applied as they arrive.
* ``lockstep``: simulated time advances one ``step_dt_s`` at a time. At step ``k`` the emulator
  sends the MAVLink messages due by ``t = k step_dt_s`` (stamped ``t``), FOLLOW_TARGET if due,
  the ground-truth record and the camera frame(s) due; then waits up to ``lockstep_timeout_s``
  of wall time until every frame delivered so far has been answered by one SET_ATTITUDE_TARGET
  (camera latency jitter can deliver two frames in one step: the step then waits for two
  answers; a timeout is counted as a lost setpoint, is no offboard signal, and clears the
  count); then
  integrates to ``t + step_dt_s``, stopping at every link event in between: each message
  leaving the transport delay (``[sim.telemetry]``) at its due time, each delayed delivery of
  an impaired link, and, with a transport delay, each stream's messages at their own rates
  (stamped with the time they sample; on the ideal link the streams are sampled at the step
  boundaries only). The telemetry a client holds when step ``k``'s frame arrives is therefore
  what a real link would have delivered by ``t``. Commands are handled whenever they arrive,
  stamped ``t``. The camera fires once per step (``sim.camera.rate_hz`` must agree).
"""

from __future__ import annotations

import asyncio
import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from sim_bridge.app import SimBridge


async def run_realtime(sim: SimBridge, duration_s: float) -> None:
    """Run ``sim`` on the wall clock for ``duration_s`` of boot time."""
    cfg = sim.cfg.sim
    tick = min(0.01, cfg.step_dt_s)
    frame_dt = 1.0 / cfg.camera.rate_hz
    ft_dt = 1.0 / cfg.agv.rate_hz
    next_frame = next_ft = 0.0
    while True:
        now = sim.now_s()
        if now >= duration_s:
            break
        sim.advance(now)
        sim.t_s = sim.state.t_s
        sim.telemetry.send_streams(now)
        if now >= next_ft:
            sim.send_follow_target(now)
            next_ft = max(next_ft + ft_dt, now)
        if now >= next_frame:
            await sim.publish_frame(sim.state.t_s)
            sim.steps += 1
            next_frame = max(next_frame + frame_dt, now)
        now2 = sim.now_s()
        await sim.deliver_frames(now2)
        sim.transport.flush(now2)
        wake = min(now + tick, sim.frame_line.next_due_s, sim.transport.next_due_s())
        await asyncio.sleep(max(0.0, wake - sim.now_s()))


async def run_lockstep(sim: SimBridge, duration_s: float) -> None:
    """Run ``sim`` in simulated time, one ``sim.step_dt_s`` at a time, for ``duration_s``."""
    cfg = sim.cfg.sim
    step = cfg.step_dt_s
    ft_dt = 1.0 / cfg.agv.rate_hz
    next_ft = 0.0
    k = 0
    while k * step < duration_s - 1e-9:
        t = k * step
        sim.t_s = t
        deliver_due(sim, t)
        sim.px4.update(t, sim.state)
        sim.note_changes(t)
        sim.telemetry.send_streams(t)
        sim.transport.flush(t)
        if t + 1e-9 >= next_ft:
            sim.send_follow_target(t)
            next_ft += ft_dt
        sim.delivered_this_step = 0
        sim.setpoint_event.clear()
        await sim.publish_frame(t)
        # the step is released once every frame delivered in it has been answered (one
        # setpoint each; a step that delivers two frames, by latency jitter, waits for
        # two). A step that delivers no frame (latency, drop) does not wait: a client that
        # answers frames has nothing to answer, and PX4 keeps the last setpoint.
        if sim.delivered_this_step and sim.unanswered > 0:
            try:
                # before any answer, a client that got the frame may still be building its
                # controller (a frame nobody got waits the usual timeout)
                first = (sim.services.setpoints == 0 and cfg.lockstep_start_timeout_s > 0
                         and sim.frame_clients > 0)
                await asyncio.wait_for(sim.setpoint_event.wait(),
                                       cfg.lockstep_start_timeout_s if first
                                       else cfg.lockstep_timeout_s)
            except TimeoutError:
                sim.timeouts += 1
                sim.unanswered = 0  # a frame left unanswered: start counting afresh
        advance_delivering(sim, (k + 1) * step)
        sim.steps += 1
        k += 1
    sim.t_s = k * step


def deliver_due(sim: SimBridge, t_s: float) -> None:
    """Lockstep: hand on every delayed datagram due by ``t_s`` (simulated time)."""
    for ml in sim.links.values():
        ml.pump(t_s)


def next_state_event_s(sim: SimBridge) -> float:
    """Lockstep: the next link event that needs the vehicle's state at its time: a delayed
    delivery (impairment; a setpoint takes effect then) or a stream message due."""
    due = [d for ml in sim.links.values() if (d := ml.next_due_s()) is not None]
    if sim.streams_in_step:
        due += [st.next_due_s() for st in sim.telemetry.streams.values()]
    return min(due, default=math.inf)


def advance_delivering(sim: SimBridge, t_target: float) -> None:
    """Lockstep: integrate to ``t_target``, stopping at every link event in between, as a
    real autopilot's links run while it flies: a delayed setpoint takes effect at its
    arrival time, a message leaves the transport delay when it is due and (with a
    transport delay, ``sim.streams_in_step``) each stream is sampled at its own rate,
    stamped with the time it samples (each to a physics step). So the telemetry a client
    holds when the next frame arrives is what a real link would have delivered by then:
    stamped at most the transport delay plus one stream period before the frame's step.
    (Streams sampled only at step boundaries, with any delay, arrived a whole step late.)"""
    while True:
        state_due = next_state_event_s(sim)
        due = min(state_due, sim.transport.next_due_s())
        if due >= t_target - 1e-9:
            break
        if state_due <= due:  # a message leaving the delay needs no state
            sim.advance(due)
        sim.t_s = due
        deliver_due(sim, due)
        sim.telemetry.send_streams(due)
        sim.transport.flush(due)
    sim.advance(t_target)
