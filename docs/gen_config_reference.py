"""Write docs/reference/config.md: every key the companion and the emulator accept.

    python docs/gen_config_reference.py            # rewrites docs/reference/config.md

The keys, their types, defaults and checks come from the validated, frozen config sections
(``companion.config.Config``, ``sim_bridge.config.EmulatorConfig``), walked field by field; the
meanings from the comments of ``config/paper.toml`` (else of the other ``config/*.toml``, else
the field's own comment or docstring); the ranges from each field's check and from the messages
of the errors the sections raise (``"rmpc.eps: must be > 0"``). Run it after adding or changing
a key; ``tests/test_docs.py`` checks that every key of ``config/*.toml`` is on the page.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import sys
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from companion import config as ccfg  # noqa: E402
from sim_bridge import config as scfg  # noqa: E402

OUT = ROOT / "docs" / "reference" / "config.md"
SKIP = {"rmpc.target_corners_m"}  # filled from [target], refused as a key

UNITS = [("_m_s2_sqrt_s", "m/s^2/sqrt(s)"), ("_per_sqrt_s", "1/sqrt(s)"), ("_m_s2", "m/s^2"),
         ("_m_s", "m/s"), ("_rad_s", "rad/s"), ("_deg_s", "deg/s"), ("_1_s", "1/s"),
         ("_per_s", "1/s"), ("_per_min", "1/min"), ("_dn_per_e", "DN/e-"), ("_dn", "DN"),
         ("_ms", "ms"), ("_us", "us"), ("_ns", "ns"), ("_s", "s"), ("_hz", "Hz"), ("_px", "px"),
         ("_deg", "deg"), ("_rad", "rad"), ("_mb", "MB"), ("_bytes", "bytes"), ("_m", "m"),
         ("_ppm", "ppm"), ("_n", "N"), ("_kg", "kg")]

# Meanings of the keys that no config file or field comments (keep them short; prefer adding the
# comment to config/paper.toml or the field, which this script reads first).
NOTES = {
    "camera.pixel_size_m": "size of one pixel of the images processed",
    "camera.width_px": "image width", "camera.height_px": "image height",
    "target.width_m": "the top's size across its heading",
    "target.height_m": "the top's height above the ground",
    "target.aruco_dictionary": ("OpenCV ArUco dictionary of the marker (`target.pattern = "
                                "\"aruco\"`)"),
    "target.aruco_id": "the marker's id in that dictionary",
    "target.mavlink_compid": "the AGV's MAVLink component id",
    "target.origin_lon_deg": "longitude of the shared local NED origin",
    "target.origin_alt_m": "altitude (AMSL) of the shared local NED origin",
    "rmpc.q_diag": "stage weights of the error state `col(s_e, v_q)` (paper's Q)",
    "rmpc.r_diag": "stage weights of the input `[r1, r2, r3, psidot_q]` (paper's R)",
    "rmpc.g_m_s2": "gravity",
    "rmpc.enable_tube": "tube rows on (diagnosis only)",
    "rmpc.enable_terminal": "terminal rows on (diagnosis only)",
    "rmpc.jit": ("compile the NLP's functions to C and cache them (off: CasADi's virtual machine, "
                 "slower)"),
    "rmpc.cache_dir": "where compiled solvers are cached, keyed by a hash of their source",
    "rmpc.max_iter": "solver iteration limit per solve",
    "rmpc.recovery_q_diag": "stage weights of the soft copy (recovery); unset: `q_diag`",
    "rmpc.recovery_eps": "terminal level of the soft copy; unset: `eps`",
    "rmpc.terminal.p_scale": "scale applied to the terminal matrix P",
    "rmpc.terminal.k_matrix": "explicit terminal gain K (with `p_matrix`); empty = compute",
    "rmpc.terminal.kappa": "kappa of Theorem 1 for explicit matrices",
    "control.thrust_min": "lowest normalised thrust ever sent",
    "control.thrust_max": "highest normalised thrust ever sent",
    "mavlink.target_system": "the autopilot's system id (PX4: 1)",
    "mavlink.target_component": "the autopilot's component id (PX4: 1)",
    "mavlink.signing_key_file": ("MAVLink 2 signing key (PX4's raw key file or 64 hex digits); "
                                 "\"\" = unsigned"),
    "mavlink.allowed_sources": ("\"host\" or \"host:port\" that may always speak for the vehicle "
                                "(routers)"),
    "mavlink.repin_after_s": "a pinned address is released after this long without a valid frame",
    "offboard.mode_retry_s": ("the OFFBOARD (or exit) request is re-sent this often until the "
                              "HEARTBEAT shows it"),
    "safety.telemetry_timeout_s": "older attitude/position telemetry is stale: level hover",
    "safety.target_lost_timeout_s": ("target not detected for this long: lost (reacquire or "
                                     "terminal law)"),
    "safety.follow_target_timeout_s": "an older FOLLOW_TARGET is not used",
    "safety.silence_after_s": ("trouble this long: stop streaming, PX4's offboard-loss failsafe "
                               "takes over"),
    "safety.reacquire_climb_rate_m_s": "climb rate while reacquiring a lost target",
    "safety.reacquire_max_height_m": "highest camera height above the target while reacquiring",
    "logging.dir": "folder of the flight logs (`companion run` without `--log`)",
    "logging.chunk_size_bytes": "MCAP chunk size",
    "logging.flush_interval_s": "the writer flushes (and fsyncs, see `fsync`) this often",
    "logging.queue_size": "messages waiting for the writer thread",
    "logging.preview_scale": "preview size factor, (0, 1]",
    "logging.preview_jpeg_quality": "preview JPEG quality",
    "sim.physics_dt_s": "physics sub-step",
    "sim.seed": "seed of every random process of the emulator",
    "sim.scenario": "scenario flown unless `--scenario` names another",
    "sim.duration_s": "simulated duration (the demo's `--duration` overrides it)",
    "sim.vehicle.max_tilt_rate_rad_s": "first-order model: largest roll/pitch rate",
    "sim.vehicle.max_yaw_rate_rad_s": "first-order model: largest yaw rate",
    "sim.vehicle.max_tilt_rad": "first-order model: largest tilt",
    "sim.vehicle.hover_thrust_error": "true hover thrust = hover_thrust (1 + this)",
    "sim.battery.max_thrust_loss": "largest loss of maximum thrust",
    "sim.disturbance.gust_amplitude_m_s2": "amplitude of the sinusoidal gust along the wind",
    "sim.disturbance.gust_period_s": "period of the gust",
    "sim.disturbance.random_bound_m_s2": "a new random acceleration in this ball every step",
    "sim.px4.com_of_loss_t_s": "PX4's COM_OF_LOSS_T: offboard signal lost after this long",
    "sim.px4.com_disarm_prflt_s": ("PX4's COM_DISARM_PRFLT: disarm if armed this long without "
                                   "take-off"),
    "sim.link.sysid": "the emulated autopilot's system id",
    "sim.link.compid": "the emulated autopilot's component id",
    "sim.link.offboard_remote": "where the offboard-API link sends (the companion)",
    "sim.link.gcs_local_port": "UDP port of the ground-station link",
    "sim.link.gcs_remote": "where the ground-station link sends",
    "sim.agv.speed_scale": ("speed scale of the path (heading rate scales with it, acceleration "
                            "with its square)"),
    "sim.agv.rate_hz": "FOLLOW_TARGET rate",
    "sim.camera.rate_hz": "camera frame rate (realtime; lockstep steps at `sim.step_dt_s`)",
    "sim.camera.noise_std": "white grey-level noise added to each frame",
    "sim.camera.blur_px": "Gaussian blur of each frame",
    "sim.impairment.seed": "seed of the impairment's random draws",
    "sim.camera_model.level": "camera preset (see the list above)",
    "sim.camera_model.clock_drift_ppm": "camera clock drift (`timestamp_clock = \"camera\"`)",
    "sim.telemetry.level": "telemetry preset (see the list above)",
    "sim.px4_control.thr_mdl_fac": "PX4's THR_MDL_FAC: motor thrust curve",
    "sim.px4_control.imu_dgyro_cutoff_hz": ("PX4's IMU_DGYRO_CUTOFF: low-pass of the gyro "
                                            "derivative"),
    "sim.px4_control.inertia_kg_m2": "airframe inertia (x, y, z)",
    "sim.px4_control.arm_xy_m": "motor arm length (quad X)",
    "sim.px4_control.km_m": "motor yaw-torque to thrust ratio",
    "sim.px4_control.motor_tau_s": "motor time constant",
    "sim.scenarios.NAME.uav_pose": "initial pose: x, y, z (m, NED), roll, pitch, yaw (rad, ZYX)",
}
for _d in ("vehicle_to_companion", "companion_to_vehicle"):
    NOTES[f"sim.impairment.{_d}.drop_p"] = "probability a datagram is dropped"
    NOTES[f"sim.impairment.{_d}.duplicate_p"] = "probability a datagram is sent twice"
    NOTES[f"sim.impairment.{_d}.reorder_p"] = "probability a datagram is held back (reordered)"
    NOTES[f"sim.impairment.{_d}.reorder_delay_s"] = "how long a reordered datagram is held back"
    NOTES[f"sim.impairment.{_d}.delay_s"] = "one-way latency"
    NOTES[f"sim.impairment.{_d}.jitter_s"] = "plus U(0, jitter_s), order kept"
    NOTES[f"sim.impairment.{_d}.corrupt_p"] = "probability a datagram is corrupted"
    NOTES[f"sim.impairment.{_d}.corrupt_bits"] = "random bits flipped in a corrupted datagram"


@dataclass
class Key:
    name: str
    type_: str
    default: str
    readers: set[str] = field(default_factory=set)
    checks: list[str] = field(default_factory=list)
    source_comment: str = ""


def _unit(name: str) -> str:
    leaf = name.rsplit(".", 1)[-1]
    for suffix, unit in UNITS:
        if leaf.endswith(suffix):
            return unit
    return ""


def _type_text(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list of {_type_text(args[0])}"
        return f"{len(args)} x {_type_text(args[0])}"
    args = typing.get_args(tp)
    if args and type(None) in args:
        return f"{_type_text(next(a for a in args if a is not type(None)))}, optional"
    return {bool: "bool", int: "int", float: "number", str: "string"}.get(tp, str(tp))


def _probe(check: Any) -> str:
    """A check's rule, read from the message it gives a value far outside any range."""
    for bad in (-1e18, 1e18, "\x00", (1e18, 1e18, 1e18), ()):
        try:
            msg = check(bad)
        except Exception:  # a check for another type
            continue
        if msg:
            return str(msg)
    return ""


def _toml(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + "}"
    return repr(v)


def _walk(cls: Any, prefix: str, reader: str, keys: dict[str, Key]) -> None:
    hints = typing.get_type_hints(cls, vars(sys.modules[cls.__module__]))
    for f in dataclasses.fields(cls):
        if f.name in ("source", "raw", "name") or not f.init:
            continue
        tp = hints[f.name]
        name = f"{prefix}.{f.name}" if prefix else f.name
        if dataclasses.is_dataclass(tp):
            _walk(tp, name, reader, keys)
            continue
        if name in SKIP:
            continue
        if f.default is not dataclasses.MISSING:
            default = "unset" if f.default is None else _toml(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            default = _toml(f.default_factory())
        else:
            default = "required"
        k = keys.setdefault(name, Key(name, _type_text(tp), default))
        k.readers.add(reader)
        check = f.metadata.get("check")
        if check is not None and (rule := _probe(check)) and rule not in k.checks:
            k.checks.append(rule)
        if not k.source_comment:
            k.source_comment = _field_comment(cls, f.name)


def _field_comment(cls: Any, name: str) -> str:
    """The comment lines right above the field in its class, or the docstring's sentence
    that names it."""
    try:
        lines, _ = inspect.getsourcelines(cls)
    except (OSError, TypeError):
        return ""
    for i, line in enumerate(lines):
        if re.match(rf"\s+{name}\s*:", line):
            block: list[str] = []
            j = i - 1
            while j > 0 and lines[j].strip().startswith("#"):
                block.insert(0, lines[j].strip().lstrip("#").strip())
                j -= 1
            if block:
                return " ".join(block)
            break
    doc = inspect.getdoc(cls) or ""
    for sentence in re.split(r"(?<=\.)\s+", " ".join(doc.split())):
        if f"``{name}``" in sentence:
            return sentence.replace("``", "`")
    return ""


def _error_rules() -> dict[str, list[str]]:
    """``key -> rules`` from the messages of every ``...Error("key: rule")`` raised in the
    companion and emulator sources."""
    rules: dict[str, list[str]] = {}
    for path in [*ROOT.glob("companion/**/*.py"), *ROOT.glob("sim_bridge/**/*.py")]:
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Call) and node.args):
                continue
            fn = node.func
            fname = fn.id if isinstance(fn, ast.Name) else getattr(fn, "attr", "")
            if not fname.endswith("Error"):
                continue
            text = _literal(node.args[0])
            m = re.match(r"^([a-z0-9_]+(?:\.[a-z0-9_]+)+)(?:\[[^\]]*\])?: (.+)$", text)
            if m and "{}" not in m.group(1):
                rule = re.sub(r"^\{\}[\s:,]*", "", m.group(2))
                rule = re.sub(r"[\s,]*\(?got \{\}\)?$", "", rule).strip(" :,")
                if rule and "{}" not in rule and rule not in rules.setdefault(m.group(1), []):
                    rules[m.group(1)].append(rule)
    return rules


def _literal(node: ast.expr) -> str:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)
    return ""


def _toml_comments(path: Path) -> tuple[dict[str, str], dict[str, str], list[str]]:
    """``(key -> comment, table -> intro, tables in order)`` of one TOML file: a key's inline
    comment (and its indented continuation lines) after the comment block right above it."""
    comments: dict[str, str] = {}
    intros: dict[str, str] = {}
    order: list[str] = []
    table = ""
    block: list[str] = []
    last_key = ""
    for raw in path.read_text().splitlines():
        line = raw.strip()
        if m := re.match(r"^\[([^\]]+)\]", line):
            table = m.group(1)
            order.append(table)
            block, last_key = [], ""
            continue
        if line.startswith("#"):
            text = line.lstrip("#").strip()
            if raw.startswith(" ") and last_key:  # continuation of an inline comment
                comments[last_key] += " " + text
            elif not set(text) <= set("-"):
                block.append(text)
            continue
        if not line:
            if block and table and table not in intros and not last_key:
                intros[table] = " ".join(block)
                block = []
            elif block and not table:
                block = []
            last_key = ""
            continue
        if m := re.match(r"^([A-Za-z0-9_\-\"]+)\s*=", line):
            key = m.group(1).strip('"')
            full = f"{table}.{key}" if table else key
            inline = ""
            if "#" in line and not re.search(r"=\s*\"[^\"]*#", line):
                inline = line.split("#", 1)[1].strip()
            comments[full] = " ".join([*block, inline]).strip()
            block, last_key = [], full
    return comments, intros, order


def _table_of(key: str) -> str:
    return key.rsplit(".", 1)[0]


def collect() -> tuple[dict[str, Key], dict[str, str], dict[str, str], list[str]]:
    keys: dict[str, Key] = {}
    _walk(ccfg.Config, "", "companion", keys)
    _walk(scfg.SimConfig, "sim", "emulator", keys)
    _walk(scfg.CameraConfig, "camera", "emulator", keys)
    _walk(scfg.TargetConfig, "target", "emulator", keys)
    _walk(scfg.ScenarioConfig, "sim.scenarios.NAME", "emulator", keys)
    for name, rules in _error_rules().items():
        if name in keys:
            keys[name].checks.extend(r for r in rules if r not in keys[name].checks)
    paper = tomllib.loads((ROOT / "config" / "paper.toml").read_text())
    comments, intros, order = _toml_comments(ROOT / "config" / "paper.toml")
    for other in sorted((ROOT / "config").glob("*.toml")):
        c, _, _ = _toml_comments(other)
        for k, v in c.items():
            if v and _lookup(paper, k) is None and not comments.get(k):
                comments[k] = v
    for k, key in keys.items():
        v = _lookup(paper, k)
        if v is not None:
            key.default = _toml(v)
    return keys, comments, intros, order


def _lookup(doc: dict[str, Any], dotted: str) -> Any:
    cur: Any = doc
    for part in dotted.replace("sim.scenarios.NAME", "sim.scenarios.paper").split("."):
        if not isinstance(cur, dict) or part not in cur:
            return None
        cur = cur[part]
    return cur


def _levels() -> dict[str, dict[str, dict[str, Any]]]:
    return {f"sim.{name}": presets for name, presets in scfg._LEVELS.items()}


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render() -> str:
    keys, comments, intros, order = collect()
    tables: dict[str, list[Key]] = {}
    for key in keys.values():
        tables.setdefault(_table_of(key.name), []).append(key)
    ranked = [t for t in order if t in tables and "scenarios." not in t]
    ranked += sorted(t for t in tables if t not in ranked)
    out = [
        "# Config keys",
        "",
        "> **Answers:** what does every key of the config files mean, in which unit, with which",
        "> default and which valid range, and which program reads it?",
        "",
        "Generated by `python docs/gen_config_reference.py` from the validated config sections",
        "(`companion/config.py`, `sim_bridge/config.py` and the core's parameter types) and the",
        "comments of `config/paper.toml`: edit those, then regenerate this page. Units are in the",
        "key names (`_m`, `_s`, `_m_s2`, `_rad_s`, ...). A bad value stops the program at start-up",
        "with an error naming the key. `default` is the value in `config/paper.toml`, else the",
        "section's own default (`unset`: the key is absent unless set; `required`: the file must",
        "set it). The companion reads every table except `[sim]`; the emulator reads `[sim]`,",
        "`[camera]` and `[target]`. A variant file starts with `base = \"paper.toml\"` and holds",
        "only the keys it changes; `--set KEY=VALUE` overrides one key on the command line.",
        "",
        "How to choose the values for a vehicle: [`guides/tune.md`](../guides/tune.md).",
        "",
    ]
    levels = _levels()
    for t in ranked:
        out += [f"## `[{t}]`", ""]
        if intros.get(t):
            out += [intros[t], ""]
        if t in levels:
            out += ["`level` presets (explicit keys override the preset's values):", ""]
            for lvl, preset in levels[t].items():
                body = ", ".join(f"`{k}` = {_toml(v)}" for k, v in preset.items()) or "all off"
                out.append(f"- `{lvl}`: {body}")
            out.append("")
        out += ["| key | default | unit | valid | read by | meaning |",
                "| --- | --- | --- | --- | --- | --- |"]
        for key in tables[t]:
            leaf = key.name[len(t) + 1:]
            meaning = comments.get(key.name, "")
            if not meaning and key.name.startswith("sim.px4_control.mc_"):
                meaning = f"PX4's {leaf.upper().replace('_DEG_S', '')}"
            meaning = meaning or NOTES.get(key.name, "")
            if key.source_comment and not meaning:
                meaning = f"{meaning} {key.source_comment}".strip()
            valid = "; ".join(key.checks) or key.type_
            if key.checks:
                valid = f"{key.type_}; {valid}"
            readers = " + ".join(sorted(key.readers))
            out.append(f"| `{leaf}` | `{_cell(key.default)}` | {_unit(key.name)} | "
                       f"{_cell(valid)} | {readers} | {_cell(meaning)} |")
        out.append("")
    return "\n".join(out)


def main() -> None:
    OUT.write_text(render())
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
