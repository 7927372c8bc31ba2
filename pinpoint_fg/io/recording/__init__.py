"""Recorded runs, format version 1 (``shared/RECORDING_FORMAT.md``): schema, validator, reader, writer.

A run is a directory with ``recording.json``, ``frames.csv`` and optional ``masks/`` and ``images/``.
Readers validate everything and raise :class:`pinpoint_fg.errors.InputError` naming the file, the row
and the column; extra columns/keys are ignored. Modules: ``schema`` (names, bounds, the records, the
format's decisions), ``png`` (mask/image file checks), ``validator`` (every problem of a run),
``reader`` (:func:`read_recording`), ``writer`` (:class:`RecordingWriter`). The names below are the
documented user API (``from pinpoint_fg.io.recording import read_recording``).
"""

from pinpoint_fg.io.recording.reader import read_recording, summarize_recording
from pinpoint_fg.io.recording.schema import FrameRecord, Recording, RecordingInfo
from pinpoint_fg.io.recording.validator import validate_run
from pinpoint_fg.io.recording.writer import RecordingWriter, replace_ground_truth, write_recording

__all__ = ["FrameRecord", "Recording", "RecordingInfo", "RecordingWriter", "read_recording", "replace_ground_truth",
           "summarize_recording", "validate_run", "write_recording"]
