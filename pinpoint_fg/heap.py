"""Keep freed heap memory for reuse instead of returning it to the system (glibc ``mallopt``).

A tracker step allocates and frees the same few large temporaries many times per frame (the conic
residual's ``(N * 21, M)`` product and its ``(N, 6, M)`` Jacobian terms are 0.5-1.7 MB at N = 50,
M = 200 pixels). With glibc's defaults a block above the mmap threshold (128 KiB, raised dynamically)
is a fresh ``mmap`` and a large free at the top of the heap is trimmed, so the next evaluation touches
new pages: measured ~770 minor page faults per 50-pose conic evaluation, about 2 ms of its 2.5 ms, and
a run of SVN on normal-01 took ~120k faults (36k with the settings below; total CPU -15 %).

:func:`keep_freed_memory` sets a fixed mmap threshold (32 MiB: blocks below it come from the heap) and
trim threshold (128 MiB of free memory at the top of the heap are kept), which also turns off glibc's
dynamic adjustment. Only memory management changes: every number a tracker computes is bitwise the
same (``scripts/step_outputs.py``). Decisions: process-wide and idempotent, called when a tracker is
built (:class:`pinpoint_fg.trackers.base.Tracker`); a no-op where the C library has no ``mallopt``
(not glibc) or when ``PINPOINT_FG_KEEP_HEAP=0``; the cost is a resident size that stays near its peak.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

#: glibc's ``mallopt`` parameter numbers (malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

#: Blocks below this many bytes are served from the heap (glibc caps the value at 32 MiB on 64-bit).
MMAP_THRESHOLD_BYTES = 32 << 20
#: Free memory at the top of the heap up to this many bytes is kept rather than returned.
TRIM_THRESHOLD_BYTES = 128 << 20

_applied: list[bool | None] = [None]  # the first call's result (later calls repeat it)


def keep_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds once per process (module docstring); True if they were set."""
    if _applied[0] is not None:
        return _applied[0]
    ok = False
    if os.environ.get("PINPOINT_FG_KEEP_HEAP", "1") != "0":
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
        except (OSError, AttributeError):  # not glibc (macOS, Windows, musl without mallopt)
            mallopt = None
        if mallopt is not None:
            mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
            mallopt.restype = ctypes.c_int
            ok = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) & bool(
                mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
    _applied[0] = ok
    return ok
