"""A Linux cgroup CPU quota for one process tree: how ``bench/cpu_budget.py`` makes the companion
feel like it runs on a smaller computer.

A child group is created under the ``cpu`` controller (cgroup v1: ``cpu.cfs_period_us`` and
``cpu.cfs_quota_us``, usage from the ``cpuacct`` controller; cgroup v2: ``cpu.max``, usage and
throttling from ``cpu.stat``). A process enters it between ``fork`` and ``exec``
(:meth:`CpuQuota.enter_self`, a ``preexec_fn``), so it is confined before it runs a line of its
own and every child it starts later (the solver processes) inherits the group.

When no cpu controller is mounted, or the group cannot be created or configured (not root, a
read-only ``/sys/fs/cgroup``, a v2 hierarchy without the cpu controller delegated), creating a
quota raises :class:`CgroupUnavailable` with the reason in words.
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path

__all__ = ["CgroupUnavailable", "CpuQuota", "controller_at", "create_quota",
           "find_cpu_controller"]

DEFAULT_PERIOD_US = 10_000


class CgroupUnavailable(RuntimeError):
    """No CPU quota can be set on this machine (the message says why)."""


@dataclass(frozen=True)
class Controller:
    """Where the cpu controller lives: ``version`` 1 or 2, the ``cpu`` hierarchy's directory
    under which a group is made, and (v1) the ``cpuacct`` one for usage, if mounted."""

    version: int
    cpu_dir: Path
    acct_dir: Path | None


def _mounts() -> list[tuple[str, str, set[str]]]:
    """(filesystem type, mount point, options) of every cgroup mount."""
    out = []
    with contextlib.suppress(OSError):
        for line in Path("/proc/mounts").read_text().splitlines():
            cols = line.split()
            if len(cols) >= 4 and cols[2] in ("cgroup", "cgroup2"):
                out.append((cols[2], cols[1], set(cols[3].split(","))))
    return out


def _own_v2_path() -> str:
    """This process's cgroup v2 path ("0::/path" in /proc/self/cgroup), "/" if unknown."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/cgroup").read_text().splitlines():
            if line.startswith("0::"):
                return line[3:] or "/"
    return "/"


def find_cpu_controller() -> Controller:
    """The cpu controller's hierarchy: v1 first (on a hybrid machine a controller bound to v1
    is absent from v2), else v2. Raises :class:`CgroupUnavailable` when neither has it."""
    mounts = _mounts()
    v1_cpu = next((m for t, m, o in mounts if t == "cgroup" and "cpu" in o), None)
    if v1_cpu is not None:
        acct = next((m for t, m, o in mounts if t == "cgroup" and "cpuacct" in o), None)
        return Controller(1, Path(v1_cpu), None if acct is None else Path(acct))
    for t, m, _ in mounts:
        if t != "cgroup2":
            continue
        controllers = (Path(m) / "cgroup.controllers").read_text().split() if (
            Path(m) / "cgroup.controllers").exists() else []
        if "cpu" not in controllers:
            continue
        return Controller(2, Path(m) / _own_v2_path().lstrip("/"), None)
    kinds = sorted({t for t, _, _ in mounts}) or ["none"]
    raise CgroupUnavailable(
        "no cgroup cpu controller is mounted (cgroup mounts found: " + ", ".join(kinds) + "; "
        "v1 needs a 'cpu' hierarchy, v2 needs 'cpu' in cgroup.controllers)")


def controller_at(path: Path) -> Controller:
    """The cpu controller of an explicit cgroup directory (a subtree delegated to this user,
    e.g. systemd's ``user@UID.service``): v2 if it lists ``cpu`` in ``cgroup.controllers``, v1
    if it has ``cpu.cfs_quota_us``. Raises :class:`CgroupUnavailable` otherwise."""
    if (path / "cgroup.controllers").is_file():
        if "cpu" in (path / "cgroup.controllers").read_text().split():
            return Controller(2, path, None)
        raise CgroupUnavailable(f"{path}: the cpu controller is not available there (not in "
                                "its cgroup.controllers)")
    if (path / "cpu.cfs_quota_us").is_file():
        acct = path if (path / "cpuacct.usage").is_file() else None
        return Controller(1, path, acct)
    raise CgroupUnavailable(f"{path}: not a cgroup directory with the cpu controller (neither "
                            "cgroup.controllers nor cpu.cfs_quota_us there)")


def _write(path: Path, text: str) -> None:
    try:
        path.write_text(text)
    except OSError as e:
        raise CgroupUnavailable(f"cannot write {text.strip()!r} to {path}: {e.strerror} "
                                "(needs root, or a cgroup delegated to this user)") from e


def _mkdir(path: Path) -> None:
    try:
        path.mkdir()
    except FileExistsError:
        pass
    except OSError as e:
        raise CgroupUnavailable(f"cannot create the cgroup {path}: {e.strerror} (needs root, "
                                "or a cgroup delegated to this user)") from e


@dataclass(frozen=True)
class CpuQuota:
    """A created group: ``fraction`` of one CPU every ``period_us``."""

    controller: Controller
    name: str
    fraction: float | None     # None: no limit (only the weight)
    period_us: int

    @property
    def cpu_group(self) -> Path:
        return self.controller.cpu_dir / self.name

    @property
    def acct_group(self) -> Path | None:
        a = self.controller.acct_dir
        if a is None or a == self.controller.cpu_dir:
            return None
        return a / self.name

    @property
    def quota_us(self) -> int | None:
        if self.fraction is None:
            return None
        return max(1000, round(self.fraction * self.period_us))  # the kernel's minimum: 1 ms

    def enter_self(self) -> None:
        """Move the calling process into the group (use as ``Popen(preexec_fn=...)``: runs in
        the child after fork, before exec, so the program and its children are confined)."""
        pid = f"{os.getpid()}\n"
        (self.cpu_group / "cgroup.procs").write_text(pid)
        if self.acct_group is not None:
            (self.acct_group / "cgroup.procs").write_text(pid)

    def usage_s(self) -> float | None:
        """CPU time used by the group's processes so far (every thread, every child, also
        those not yet reaped), None when not measurable (v1 without cpuacct)."""
        if self.controller.version == 2:
            v = self.stat().get("usage_usec")
            return None if v is None else v * 1e-6
        acct = self.acct_group or (self.cpu_group if self.controller.acct_dir else None)
        if acct is None:
            return None
        try:
            return int((acct / "cpuacct.usage").read_text()) * 1e-9
        except (OSError, ValueError):
            return None

    def stat(self) -> dict[str, int]:
        """``cpu.stat`` (nr_periods, nr_throttled, throttled_time [ns, v1] or throttled_usec
        [v2], usage_usec [v2], ...)."""
        out: dict[str, int] = {}
        with contextlib.suppress(OSError):
            for line in (self.cpu_group / "cpu.stat").read_text().splitlines():
                k, _, v = line.partition(" ")
                with contextlib.suppress(ValueError):
                    out[k] = int(v)
        return out

    def throttled_s(self) -> float | None:
        st = self.stat()
        if "throttled_usec" in st:
            return st["throttled_usec"] * 1e-6
        if "throttled_time" in st:
            return st["throttled_time"] * 1e-9
        return None

    def pids(self) -> list[int]:
        with contextlib.suppress(OSError):
            return [int(p) for p in (self.cpu_group / "cgroup.procs").read_text().split()]
        return []

    def remove(self) -> None:
        """Remove the group. Whatever still runs in it was started through :meth:`enter_self`
        (a solver process its parent left behind): killed first, as a group cannot be removed
        while it holds a process."""
        for pid in self.pids():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)
        for group in (self.cpu_group, self.acct_group):
            if group is None:
                continue
            for _ in range(50):
                try:
                    group.rmdir()
                    break
                except FileNotFoundError:
                    break
                except OSError:
                    time.sleep(0.1)


def create_quota(fraction: float | None, name: str, period_us: int = DEFAULT_PERIOD_US,
                 weight_factor: float = 1.0, parent: Path | None = None) -> CpuQuota:
    """Create the group ``name`` limited to ``fraction`` of one CPU (> 1: several CPUs; None:
    no limit) every ``period_us``, its scheduling weight ``weight_factor`` x the default (the
    group competes with every other runnable task as ONE task of that weight: at 1 on a busy
    machine it gets less than its quota), under ``parent`` (default: the cpu hierarchy found
    in /proc/mounts). Raises :class:`CgroupUnavailable` (why, in words) or ValueError."""
    if fraction is not None and not 0.0 < fraction <= 64.0:
        raise ValueError(f"fraction {fraction}: must be in (0, 64]")
    if not 1000 <= period_us <= 1_000_000:
        raise ValueError(f"period {period_us} us: must be in [1000, 1000000]")
    if not 0.01 <= weight_factor <= 100.0:
        raise ValueError(f"weight factor {weight_factor}: must be in [0.01, 100]")
    ctl = find_cpu_controller() if parent is None else controller_at(parent)
    q = CpuQuota(ctl, name, fraction, period_us)
    if ctl.version == 2:
        # the cpu controller must be enabled for the children of the group we create in
        _write(ctl.cpu_dir / "cgroup.subtree_control", "+cpu\n")
        _mkdir(q.cpu_group)
        try:
            quota = "max" if fraction is None else str(q.quota_us)
            _write(q.cpu_group / "cpu.max", f"{quota} {period_us}\n")
            _write(q.cpu_group / "cpu.weight", f"{round(min(10000, 100 * weight_factor))}\n")
        except CgroupUnavailable:
            q.remove()
            raise
        return q
    _mkdir(q.cpu_group)
    try:
        _write(q.cpu_group / "cpu.cfs_period_us", f"{period_us}\n")
        _write(q.cpu_group / "cpu.cfs_quota_us", f"{-1 if fraction is None else q.quota_us}\n")
        _write(q.cpu_group / "cpu.shares", f"{round(1024 * weight_factor)}\n")
        if q.acct_group is not None:
            _mkdir(q.acct_group)
    except CgroupUnavailable:
        q.remove()
        raise
    return q
