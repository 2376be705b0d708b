"""Telemetry: MCAP recordings of every control tick, run summaries, figures.

Sits beside the runtime and imports nothing of DentiBot but ``dentibot.errors``: the runtime
builds the rows (:mod:`~dentibot.telemetry.schema`), hands them to a
:class:`~dentibot.telemetry.recorder.McapRecorder` and a
:class:`~dentibot.telemetry.summary.SummaryAccumulator`; ``dentibot report`` and
``dentibot plot`` read the file back (:func:`~dentibot.telemetry.reader.read_recording`).
Plotting (matplotlib) is imported on demand: ``from dentibot.telemetry.plots import ...``.
"""

from dentibot.telemetry.reader import MessageStream, Recording, read_recording
from dentibot.telemetry.recorder import McapRecorder
from dentibot.telemetry.schema import (
    END_STATUSES,
    EVENT_FIELDS,
    TICK_FIELDS,
    TOPICS,
    Field,
    TelemetryError,
    default_row,
    json_schema,
    validate_row,
)
from dentibot.telemetry.summary import (
    RunSummary,
    StepSummary,
    SummaryAccumulator,
    summarize_file,
    summarize_recording,
    summary_json,
    summary_table,
)

__all__ = [
    "END_STATUSES", "EVENT_FIELDS", "TICK_FIELDS", "TOPICS", "Field", "McapRecorder", "MessageStream",
    "Recording", "RunSummary", "StepSummary", "SummaryAccumulator", "TelemetryError",
    "default_row", "json_schema", "read_recording", "summarize_file", "summarize_recording", "summary_json",
    "summary_table", "validate_row",
]
