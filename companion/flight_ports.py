"""A lockstep flight's ports, chosen by the processes that bind them (no probe race).

Probing a free port (bind to 0, read the number, close) and handing the number to a child
races: between the close and the child's bind another process (a second campaign worker
probing at the same moment) may be handed the same number, and one of the two children then
cannot bind (the emulator exits 2) or, worse, talks to the other flight. So nothing is probed:

* the companion listens on ``udpin:127.0.0.1:0`` and ``--truth-port 0`` and writes the ports
  the kernel gave it into its ``--ready-file`` (:func:`write_ready`, read back with
  :func:`read_ready`); the emulator, started after that, sends to them;
* the emulator binds its own UDP links on port 0 (the companion learns the emulator's address
  from its first datagram, as from PX4);
* the camera frame server's port is the one the companion must be told before the emulator
  exists: the orchestrator binds and listens on it (port 0) and hands the listening socket to
  the emulator as an inherited file descriptor (``sim-bridge --frame-fd``), so the port is held
  from its choice to the flight's end; a companion connecting before the emulator serves waits
  in the listen backlog;
* the emulator's GCS link sends to a UDP socket the orchestrator holds for the flight (no
  ground station listens in a demo; a held socket makes sure nobody else's does either).
"""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

__all__ = ["FlightSockets", "ReadyPorts", "read_ready", "write_ready"]

LOOPBACK = "127.0.0.1"


@dataclass(frozen=True)
class ReadyPorts:
    """What the companion's ready file says: the UDP ports it listens on (``None``: not
    given, e.g. no ``--truth-port``)."""

    mavlink_port: int | None
    truth_port: int | None


def write_ready(path: Path, mavlink_address: tuple[str, int] | None,
                truth_port: int | None) -> None:
    """Write the ready file (``ready`` then ``mavlink_port N`` / ``truth_port N`` lines) in one
    rename, so that a reader polling for it never sees half of it."""
    lines = ["ready"]
    if mavlink_address is not None:
        lines.append(f"mavlink_port {mavlink_address[1]}")
    if truth_port is not None:
        lines.append(f"truth_port {truth_port}")
    tmp = path.with_name(path.name + f".{os.getpid()}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(path)


def read_ready(path: Path) -> ReadyPorts | None:
    """The ports of the ready file ``path``; ``None`` while there is none."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return None
    fields = dict(ln.split(None, 1) for ln in text.splitlines()[1:] if " " in ln)

    def port(key: str) -> int | None:
        value = fields.get(key)
        if value is None:
            return None
        n = int(value)
        if not 0 < n < 65536:
            raise ValueError(f"{path}: {key} {value} is not a port")
        return n

    return ReadyPorts(port("mavlink_port"), port("truth_port"))


class FlightSockets:
    """The sockets the orchestrator holds for one flight: the camera frame server's listening
    socket (handed to the emulator: :attr:`frame_fd`) and the GCS link's sink. Both are bound
    to port 0 on loopback (the kernel picks a port no socket holds) and closed by
    :meth:`close` (or the ``with`` block's end)."""

    def __init__(self) -> None:
        self.frame = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.gcs_sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.frame.bind((LOOPBACK, 0))
            self.frame.listen(8)
            # the child inherits it (subprocess's pass_fds); the frame server makes it
            # non-blocking itself
            self.frame.set_inheritable(True)
            self.gcs_sink.bind((LOOPBACK, 0))
        except BaseException:
            self.close()
            raise

    @property
    def frame_port(self) -> int:
        return int(self.frame.getsockname()[1])

    @property
    def frame_fd(self) -> int:
        return self.frame.fileno()

    @property
    def gcs_sink_port(self) -> int:
        return int(self.gcs_sink.getsockname()[1])

    def close(self) -> None:
        self.frame.close()
        self.gcs_sink.close()

    def __enter__(self) -> FlightSockets:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
