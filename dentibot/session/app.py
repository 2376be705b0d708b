"""The terminal UI of ``dentibot session`` (textual): live panel, message log, command line.

- The panel is recomputed by a textual timer (``refresh_hz``, 5 Hz by default) from
  :meth:`SessionController.snapshot`: it reads the last telemetry row and the counters, never
  waits for the control task. The screen is then repainted one changed line at a time, every
  ``PAINT_S``: a repaint runs in the control task's event loop, and one line (about 1 ms of
  CPU in a real terminal) fits in the slack of a 2 ms tick where the whole panel (two steps of
  about 1.7 ms) did not: measured in tmux at 5 Hz, 9 overruns in 9 461 ticks instead of 241.
- The command line completes (the grey suggestion; Tab or Right accepts it, Tab lists the
  choices when there are several) and keeps a history (Up / Down). Commands run one after the
  other, in the order typed, in a worker: the screen stays live while a command waits for the
  control task.
- Immediate (not queued behind a running command): ``estop``, ``quit``, space on an empty
  command line (pause / resume), Esc (stop safely: retract if treating, then stop), Ctrl+Q or
  Ctrl+C (quit safely).
"""

from __future__ import annotations

import asyncio
from typing import ClassVar

from rich.text import Text
from textual import events
from textual.app import App, ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Vertical
from textual.suggester import Suggester
from textual.widgets import Input, RichLog, Static

from dentibot.session.commands import completions
from dentibot.session.controller import Reply, SessionController
from dentibot.session.panel import LINES, render_lines

#: Seconds between two one-line repaints (longer than a 60 Hz frame: one line per frame).
PAINT_S = 0.02
#: Commands run at once, not queued behind a running one.
QUIT_WORDS = {"quit", "exit", "q"}
ESTOP_WORDS = {"estop", "e-stop"}
STYLES = {"ok": "green", "refused": "bold yellow", "error": "bold red", "info": "",
          "event": "cyan"}


class CommandSuggester(Suggester):
    """The first completion of the line typed so far (shown in grey)."""

    def __init__(self) -> None:
        super().__init__(use_cache=False, case_sensitive=True)

    async def get_suggestion(self, value: str) -> str | None:
        found = completions(value)
        return found[0] if found else None


class CommandInput(Input):
    """The command line: completion, history, and space = pause/resume when empty."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("up", "history(-1)", "previous command", show=False),
        Binding("down", "history(1)", "next command", show=False),
        Binding("tab", "complete", "complete", show=False),
    ]

    def __init__(self, **kw) -> None:
        super().__init__(suggester=CommandSuggester(), **kw)
        self.cursor_blink = False     # a blinking cursor redraws twice a second for nothing
        self.history: list[str] = []
        self._hist_pos = 0

    async def _on_key(self, event: events.Key) -> None:
        if event.key == "space" and not self.value:
            event.stop()
            event.prevent_default()
            self.app.action_toggle_pause()
            return
        await super()._on_key(event)

    def remember(self, line: str) -> None:
        if line and (not self.history or self.history[-1] != line):
            self.history.append(line)
        self._hist_pos = len(self.history)

    def action_history(self, step: int) -> None:
        if not self.history:
            return
        self._hist_pos = min(max(self._hist_pos + step, 0), len(self.history))
        self.value = self.history[self._hist_pos] if self._hist_pos < len(self.history) else ""
        self.cursor_position = len(self.value)

    def action_complete(self) -> None:
        found = completions(self.value)
        if len(found) == 1:
            self.value = found[0]
        elif found:
            common = _common_prefix(found)
            if len(common) > len(self.value):
                self.value = common
            else:
                self.app.show(Reply("info", "  ".join(f.rsplit(" ", 1)[-1] for f in found)))
        self.cursor_position = len(self.value)


def _common_prefix(words: list[str]) -> str:
    first, last = min(words), max(words)
    n = 0
    while n < min(len(first), len(last)) and first[n] == last[n]:
        n += 1
    return first[:n]


class SessionApp(App[int]):
    """``dentibot session``: drive DentiBot step by step through its state machine."""

    TITLE = "DentiBot session"
    ENABLE_COMMAND_PALETTE = False       # Esc and Ctrl+P belong to the session
    CSS = f"""
    #panel {{ height: {LINES + 2}; border: round $accent; padding: 0 1; }}
    #panel Static {{ height: 1; }}
    #log {{ height: 1fr; border: round $panel; }}
    #command {{ dock: bottom; }}
    """
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("escape", "safe_stop", "stop safely", priority=True),
        Binding("ctrl+q", "quit_safely", "quit", priority=True),
        Binding("ctrl+c", "quit_safely", "quit", show=False, priority=True),
    ]

    def __init__(self, controller: SessionController, *, refresh_hz: float = 5.0,
                 startup: tuple[str, ...] = ()) -> None:
        super().__init__()
        self.controller = controller
        self.refresh_hz = refresh_hz
        self.startup = startup
        #: every line shown in the log, as plain text (what the operator read)
        self.transcript: list[str] = []
        self._quitting = False
        self._lines: asyncio.Queue[str] = asyncio.Queue()
        self._commands_running = 0
        self._shown: list[Text | None] = [None] * LINES    # what each panel line shows
        self._due: dict[int, Text] = {}                     # line -> text still to paint

    def compose(self) -> ComposeResult:
        with Vertical(id="panel"):
            for i in range(LINES):
                yield Static(id=f"panel-{i}")
        yield RichLog(id="log", wrap=True, markup=False, max_lines=2000)
        yield CommandInput(id="command", placeholder=(
            "command (help) - Tab completes, Up/Down history, space pauses/resumes, "
            "Esc stops safely, Ctrl+Q quits"))

    def on_mount(self) -> None:
        self.begin_capture_print(self, stdout=False, stderr=True)   # library logs -> log
        self._panel = [self.query_one(f"#panel-{i}", Static) for i in range(LINES)]
        self.set_interval(1.0 / self.refresh_hz, self.refresh_panel)
        self.set_interval(PAINT_S, self._paint_one)
        self.refresh_panel()
        self.show(Reply("info", "DentiBot session: " + self.controller.source
                        + ". Type 'connect', then 'calibrate load'; 'help' lists commands."))
        self.query_one(CommandInput).focus()
        self.run_worker(self._commands(), group="commands", name="command queue")
        for line in self.startup:
            self.submit(line)

    # ---------------------------------------------------------------- view
    def refresh_panel(self) -> None:
        """Recompute the panel; its changed lines are painted one by one (``_paint_one``)."""
        for i, line in enumerate(render_lines(self.controller.snapshot())):
            if line != self._shown[i]:
                self._due[i] = line
            else:
                self._due.pop(i, None)
        self._drain()

    def _paint_one(self) -> None:
        if self._due:
            i = next(iter(self._due))
            line = self._due.pop(i)
            self._shown[i] = line
            # one line of fixed size: no layout pass, only its cells are redrawn
            self._panel[i].update(line, layout=False)

    @property
    def painting(self) -> bool:
        """Panel lines changed and not painted yet."""
        return bool(self._due)

    @property
    def panel_text(self) -> str:
        """What the panel shows now (plain text)."""
        return "\n".join("" if t is None else t.plain for t in self._shown)

    def _drain(self) -> None:
        """The controller's messages (events, steps that ended), oldest first."""
        c = self.controller
        while c.messages:
            self._write(Reply(*c.messages.popleft()))

    def show(self, reply: Reply) -> None:
        self._drain()                         # what happened before comes first
        self._write(reply)

    def _write(self, reply: Reply) -> None:
        log = self.query_one("#log", RichLog)
        for line in reply.text.splitlines() or [""]:
            self.transcript.append(line)
            log.write(Text(line, style=STYLES.get(reply.kind, "")))

    def on_print(self, event: events.Print) -> None:
        if event.text.strip():
            self.show(Reply("info", event.text.rstrip()))

    # ---------------------------------------------------------------- commands
    def on_input_submitted(self, event: Input.Submitted) -> None:
        line = event.value.strip()
        inp = self.query_one(CommandInput)
        inp.remember(line)
        inp.value = ""
        if line:
            self.submit(line)

    def submit(self, line: str) -> None:
        """Run ``line`` after the commands before it (estop and quit at once)."""
        self.show(Reply("info", f"> {line}"))
        head = line.split()[0].lower()
        if head in QUIT_WORDS:
            self.run_worker(self._quit(), group="immediate")
        elif head in ESTOP_WORDS:
            self.run_worker(self._run(self.controller.execute(line)), group="immediate")
        else:
            self._lines.put_nowait(line)

    async def _commands(self) -> None:
        while True:
            line = await self._lines.get()
            await self._run(self.controller.execute(line))

    @property
    def pending(self) -> int:
        """Commands typed and not finished yet (queued or running)."""
        return self._lines.qsize() + self._commands_running

    async def _run(self, replies) -> None:
        """Await a command's replies and show them; a bug shows as an error, the session
        (and the control task) go on."""
        self._commands_running += 1
        try:
            result = await replies
            for reply in result if isinstance(result, list) else [result]:
                self.show(reply)
        except Exception as exc:  # noqa: BLE001 - the screen must survive a failed command
            self.show(Reply("error", f"command failed: {type(exc).__name__}: {exc}"))
        finally:
            self._commands_running -= 1
            self.refresh_panel()

    def action_toggle_pause(self) -> None:
        self.show(Reply("info", "> (space) pause / resume"))
        self.run_worker(self._run(self.controller.toggle_pause()), group="immediate")

    def action_safe_stop(self) -> None:
        self.show(Reply("info", "> (Esc) stop safely"))
        self.run_worker(self._run(self.controller.safe_stop()), group="immediate")

    def action_quit_safely(self) -> None:
        self.show(Reply("info", "> quit"))
        self.run_worker(self._quit(), group="immediate")

    async def _quit(self) -> None:
        if self._quitting:
            return
        self._quitting = True
        self.show(Reply("info", "quitting: stopping safely first ..."))
        self.refresh_panel()
        reply = await self.controller.shutdown()
        self.show(reply)
        self.refresh_panel()
        self.exit(0)
