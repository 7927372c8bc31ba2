"""pinpoint_fg.heap: glibc's thresholds are set once, and freed large blocks are reused without page faults."""

from __future__ import annotations

import platform
import subprocess
import sys
import textwrap

import pytest

from pinpoint_fg.heap import keep_freed_memory

GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"

# allocate, touch and free a 2 MB array 200 times; print the minor page faults of the loop
_LOOP = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from pinpoint_fg.heap import keep_freed_memory
    applied = keep_freed_memory() if sys.argv[1] == "1" else False
    src = np.ones((50, 7, 3, 250))
    for _ in range(3):
        (src * 2.0).sum()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(200):
        a = src * 2.0  # 2.1 MB, freed at the next assignment
        b = src + 1.0
        del a, b
    print(int(applied), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
""")


def _faults(apply: bool) -> tuple[int, int]:
    out = subprocess.run([sys.executable, "-c", _LOOP, "1" if apply else "0"], capture_output=True, text=True,
                         check=True).stdout.split()
    return int(out[0]), int(out[1])


def test_keep_freed_memory_is_idempotent():
    first = keep_freed_memory()
    assert isinstance(first, bool)
    assert keep_freed_memory() is first


@pytest.mark.skipif(not GLIBC, reason="mallopt thresholds are glibc's")
def test_freed_blocks_are_reused_without_page_faults():
    applied, faults = _faults(True)
    assert applied == 1
    # 200 iterations x 2 arrays x ~520 pages each would fault ~200k times if every block were fresh
    assert faults < 2000


@pytest.mark.skipif(not GLIBC, reason="mallopt thresholds are glibc's")
def test_switch_off_by_environment():
    code = "from pinpoint_fg.heap import keep_freed_memory; print(keep_freed_memory())"
    env = {"PINPOINT_FG_KEEP_HEAP": "0", "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.strip() == "False"
