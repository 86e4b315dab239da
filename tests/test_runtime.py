"""Allocator setting for training: large freed tensors stay in glibc's heap for reuse instead of being unmapped."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

# mallinfo2().hblkhd: bytes in blocks that glibc mmapped individually (and unmaps, and faults in again, when freed)
PROBE = """
import ctypes, torch
from framework.runtime import reuse_freed_memory
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks",
                 "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
applied = reuse_freed_memory()
before = libc.mallinfo2().hblkhd
t = torch.ones(4 * 2**20)  # 16 MB
print(applied, libc.mallinfo2().hblkhd - before)
"""


def _probe(env_extra: dict[str, str]) -> tuple[bool, int]:
    env = dict(os.environ, **env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=120)
    if "mallinfo2" in out.stderr:
        pytest.skip("glibc without mallinfo2")
    assert out.returncode == 0, out.stderr[-2000:]
    applied, mapped = out.stdout.split()
    return applied == "True", int(mapped)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc allocator setting")
def test_large_tensors_come_from_the_heap_not_from_fresh_mappings():
    applied, mapped = _probe({})
    assert applied and mapped == 0
    applied_default, mapped_default = _probe({"SPLATRIG_MALLOC": "system"})
    assert not applied_default and mapped_default >= 16 * 2**20  # glibc's default maps every such block anew
