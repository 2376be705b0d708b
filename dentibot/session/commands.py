"""The session's command language: parsing, parameters, help and completion (no I/O).

A command line is words separated by blanks (quotes as in a shell)::

    drill tau_d=40 rpm=60 strategy=automated
    step drag duration_s=2 hand_force_n=0,0,-1
    record start runs/bench.mcap

``key=value`` parameters are YAML scalars or lists (``40``, ``automated``, ``[0, 0, -1]``;
``0,0,-1`` is read as a list too). Parameters of ``align``, ``drill`` and ``step KIND`` are the
protocol schema's step fields (:data:`dentibot.protocol.schema.STEP_MODELS`) and are validated
by the same models, so a bad value gives the same field, value and limit as in a protocol
file. A field may be named without its unit suffix: ``tau_d`` for ``tau_d_mnm``, ``fz`` for
``fz_n``, ``duration`` for ``duration_s``; ``rounds=[60, 40]`` means rounds of 60 s and 40 s.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ValidationError

from dentibot import yamlfile
from dentibot.errors import DentibotError
from dentibot.protocol.loader import describe_error
from dentibot.protocol.schema import STEP_MODELS, Protocol, Step

#: Unit suffixes a parameter may be given without (``tau_d`` -> ``tau_d_mnm``).
UNIT_SUFFIXES = ("_mnm", "_n", "_mm", "_s", "_deg")


@dataclass(frozen=True)
class CommandSpec:
    name: str
    usage: str
    short: str
    help: str
    #: the second word when the command has sub-commands (``calibrate tcp|load``)
    subs: tuple[str, ...] = ()
    #: the protocol step model whose fields are the parameters (``align``, ``drill``)
    step: str | None = None
    #: needs a connection to the devices
    needs_connection: bool = True


_SPECS = (
    CommandSpec("connect", "connect [DEVICES.yaml] [resume-arm]",
                "open the devices (built-in simulator by default)",
                "open the devices: the built-in simulator, or the drivers of a device "
                "configuration (the session's --devices when given); resume-arm resumes an "
                "arm found paused, once the workspace is clear (an arm in error is refused)",
                needs_connection=False),
    CommandSpec("calibrate", "calibrate load | calibrate tcp",
                "TCP (pedal at each pose) or load identification",
                "load: the load-identification routine (state calibrating.load, back to idle "
                "when done); tcp: hold the file tip on one fixed point, press the pedal in each "
                "of several orientations (thesis 3.4, eq 3.21-3.23), back to idle when solved",
                subs=("load", "tcp")),
    CommandSpec("pedal", "pedal",
                "press the foot pedal (simulator)",
                "one press of the simulated foot pedal (TCP calibration records a pose); with "
                "devices, press the real pedal"),
    CommandSpec("drag", "drag",
                "dragging: the arm follows the hand",
                "dragging: the arm yields to the hand at the grip (Table 4.3 dragging "
                "admittance) until the next command; with the file in the canal, at the file "
                "tip with self-alignment's gains"),
    CommandSpec("align", "align [fz_n=1.0] [rpm=0] [config=A|B|C] [tau_d_mnm=40]",
                "self-alignment, f_d = (0, 0, fz)",
                "self-alignment with f_d = (0, 0, fz) until the next command (config: thesis "
                "Table 6.4 column)", step="align"),
    CommandSpec("drill", "drill [strategy=automated] [tau_d_mnm=40] [rpm=60] [fz_min_n=-0.5] "
                "[fz_max_n=0.5] [rounds=[60,40]] ...",
                "drill to the working length (chapter-5 strategy)",
                "drill with a chapter-5 strategy: one pass to the working length, then "
                "retract (or rounds of passes, each for its duration in s)", step="drill"),
    CommandSpec("pause", "pause",
                "file stopped, no feed", "pause the treatment: file stopped, no feed, still compliant"),
    CommandSpec("resume", "resume",
                "drill on after a pause", "resume drilling after a pause"),
    CommandSpec("reverse", "reverse",
                "turn the file back 90 deg", "turn the file back 90 deg now (inverse rotation, 5.2)"),
    CommandSpec("retract", "retract",
                "withdraw the file and finish", "withdraw the file from the canal and finish the treatment"),
    CommandSpec("stop", "stop",
                "back to idle at once", "back to idle at once (Esc: retract first, then stop)"),
    CommandSpec("estop", "estop",
                "software emergency stop",
                "software emergency stop: file and arm stopped, fault latched (reset leaves it)"),
    CommandSpec("reset", "reset",
                "leave fault", "leave fault (needs the emergency stop released)"),
    CommandSpec("record", "record start [PATH] | record stop",
                "MCAP recording of every tick",
                "record every tick and event to an MCAP file (default runs/session-TIME.mcap)",
                subs=("start", "stop")),
    CommandSpec("step", "step KIND [key=value ...] | step N",
                "one protocol step",
                "run one protocol step (calibrate_load, drag, align, drill) validated like a "
                "protocol file, or step N of the session's protocol"),
    CommandSpec("status", "status",
                "state, what it takes, timing, recording", "state, what it takes, faults, timing and recording",
                needs_connection=False),
    CommandSpec("help", "help [COMMAND]",
                "this list, or one command in full", "commands and keys", needs_connection=False),
    CommandSpec("quit", "quit",
                "stop safely, close everything, exit",
                "stop safely (retract if treating, then stop), close the recording and the "
                "devices, exit", needs_connection=False),
)
COMMANDS: dict[str, CommandSpec] = {s.name: s for s in _SPECS}
ALIASES = {"exit": "quit", "q": "quit", "?": "help", "e-stop": "estop", "run": "step"}

KEYS_HELP = (
    "keys: space (on an empty line) pauses / resumes; Esc stops safely (retract, then stop); "
    "Tab completes; Up/Down history; Ctrl+Q quits (safely)")


class CommandError(DentibotError):
    """A command line that cannot be parsed or whose parameters are invalid."""


@dataclass(frozen=True)
class Command:
    name: str
    sub: str | None = None
    args: tuple[str, ...] = ()
    params: dict[str, Any] = field(default_factory=dict)


def _value(text: str) -> Any:
    """A parameter's value read as YAML (strictly: :mod:`dentibot.yamlfile`), else the text."""
    try:
        v, _ = yamlfile.parse(text, "command")
    except yamlfile.YamlFileError:
        return text
    if isinstance(v, str) and "," in v:          # 0,0,-1 -> [0, 0, -1]
        try:
            lst, _ = yamlfile.parse(f"[{text}]", "command")
        except yamlfile.YamlFileError:
            return v
        return lst
    return v


def parse(line: str) -> Command | None:
    """One command line -> :class:`Command` (None for a blank line)."""
    try:
        words = shlex.split(line, comments=True)
    except ValueError as exc:
        raise CommandError(f"cannot read the line: {exc}") from None
    if not words:
        return None
    head = words[0].lower()
    name = ALIASES.get(head, head)
    spec = COMMANDS.get(name)
    if spec is None:
        raise CommandError(f"unknown command '{words[0]}'; commands: {', '.join(COMMANDS)} "
                           "('help COMMAND' for one)")
    rest = words[1:]
    sub = None
    if spec.subs:
        if not rest or rest[0].lower() not in spec.subs:
            got = f"'{rest[0]}'" if rest else "nothing"
            raise CommandError(f"'{name}' needs one of {' | '.join(spec.subs)} "
                               f"(got {got}); usage: {spec.usage}")
        sub = rest[0].lower()
        rest = rest[1:]
    args: list[str] = []
    params: dict[str, Any] = {}
    for w in rest:
        key, eq, val = w.partition("=")
        if eq and key:
            if key in params:
                raise CommandError(f"parameter '{key}' given twice")
            params[key] = _value(val)
        else:
            args.append(w)
    return Command(name, sub, tuple(args), params)


# ---------------------------------------------------------------------------- parameters
def step_fields(kind: str) -> tuple[str, ...]:
    return tuple(STEP_MODELS[kind].model_fields)


def _canonical(kind: str, key: str) -> str:
    fields = step_fields(kind)
    if key in fields:
        return key
    for suffix in UNIT_SUFFIXES:
        if key + suffix in fields:
            return key + suffix
    return key           # unknown: the model reports it ("unknown key")


def validate_step(kind: str, params: dict[str, Any],
                  protocol: Protocol | None = None) -> BaseModel:
    """``params`` as the protocol's ``kind`` step (``drill``, ``align`` ...), or CommandError
    naming the field, the value and the limit (the protocol loader's wording). The step is
    also held to ``protocol``'s cross-field rules (e.g. tau_d below its torque limit), as if
    it were the protocol's only step (default: the protocol defaults)."""
    if kind not in STEP_MODELS:
        raise CommandError(f"unknown step '{kind}'; steps: {', '.join(STEP_MODELS)}")
    data: dict[str, Any] = {}
    for key, val in params.items():
        name = _canonical(kind, key)
        if name in data:
            raise CommandError(f"parameter '{name}' given twice")
        if name == "rounds" and isinstance(val, list):
            val = [{"duration_s": r} if isinstance(r, int | float) else r for r in val]
        data[name] = val
    try:
        spec = STEP_MODELS[kind].model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = ".".join(str(x) for x in err["loc"])
            problems.append(f"{kind}.{loc}: {describe_error(err)}")
        raise CommandError("; ".join(problems)) from None
    base = protocol or Protocol(name="session", steps=[Step(**{kind: spec})])
    alone = base.model_copy(update={"steps": [Step(**{kind: spec})]})
    problems = [f"{'.'.join(map(str, (kind, *loc[3:])))}: {text}"
                for loc, text in alone.cross_checks() if loc[:1] == ("steps",)]
    if problems:
        raise CommandError("; ".join(problems))
    return spec


# ---------------------------------------------------------------------------- help
def help_text(name: str | None = None) -> str:
    if name:
        spec = COMMANDS.get(ALIASES.get(name.lower(), name.lower()))
        if spec is None:
            raise CommandError(f"no command '{name}'; commands: {', '.join(COMMANDS)}")
        text = f"{spec.usage}\n  {spec.help}"
        if spec.step:
            text += f"\n  parameters: {', '.join(step_fields(spec.step))}"
        if spec.name == "step":
            text += "\n  steps: " + "; ".join(
                f"{k}({', '.join(step_fields(k)) or 'no parameters'})" for k in STEP_MODELS)
        return text
    usage = [s.usage if len(s.usage) <= 36 else f"{s.name} [key=value ...]" for s in _SPECS]
    width = max(map(len, usage))
    lines = [f"{u:<{width}}  {s.short}" for u, s in zip(usage, _SPECS, strict=True)]
    lines.append("('help COMMAND' for its parameters)")
    return "\n".join([*lines, KEYS_HELP])


# ---------------------------------------------------------------------------- completion
def completions(line: str) -> list[str]:
    """Whole-line completions of ``line`` (first = the suggestion shown while typing)."""
    words = line.split(" ")
    if len(words) == 1:
        return [n for n in COMMANDS if n.startswith(words[0].lower()) and n != words[0]]
    spec = COMMANDS.get(ALIASES.get(words[0].lower(), words[0].lower()))
    if spec is None:
        return []
    head = " ".join(words[:-1]) + " "
    last = words[-1]
    if spec.subs and len(words) == 2:
        return [head + s for s in spec.subs if s.startswith(last) and s != last]
    kind = spec.step
    if spec.name == "step":
        if len(words) == 2:
            return [head + k for k in STEP_MODELS if k.startswith(last) and k != last]
        kind = words[1] if words[1] in STEP_MODELS else None
    if kind is None or "=" in last:
        return []
    given = {w.partition("=")[0] for w in words[1:-1]}
    return [head + f + "=" for f in step_fields(kind)
            if f.startswith(last) and f not in given]
