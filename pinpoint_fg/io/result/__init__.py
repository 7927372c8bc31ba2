"""Tracking results, format version 1 (``shared/RECORDING_FORMAT.md``, second half).

Modules: ``schema`` (the files, columns and records of a result), ``particles`` (particles.npz and its
crash journal), ``writer`` (:class:`ResultWriter`, frame by frame), ``reader`` (:func:`read_result`,
:func:`read_modes`). The names below are the documented user API
(``from pinpoint_fg.io.result import read_result, read_modes``).
"""

from pinpoint_fg.estimate import Estimate
from pinpoint_fg.io.result.reader import expand_result_dirs, read_modes, read_result
from pinpoint_fg.io.result.schema import ModeHistory, Result
from pinpoint_fg.io.result.writer import ResultWriter

__all__ = ["Estimate", "ModeHistory", "Result", "ResultWriter", "expand_result_dirs", "read_modes", "read_result"]
