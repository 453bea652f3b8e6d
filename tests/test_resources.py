"""The allocator policy of training (`gsbench.resources.keep_freed_memory`): freed memory is reused, not
unmapped and faulted in again."""

import subprocess
import sys

import pytest

from gsbench.resources import keep_freed_memory

BLOCK = 64 << 20  # over glibc's largest dynamic mmap threshold (32 MiB), so mapped by default
PAGES = BLOCK // 4096

# A fresh process (the policy is process-wide): allocate, touch and free the block once, then count the minor
# page faults of doing it again.
SECOND_ALLOCATION_FAULTS = f"""
import resource, sys
from gsbench.resources import keep_freed_memory
if sys.argv[1] == "keep":
    assert keep_freed_memory()
def faults():
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    block = bytearray({BLOCK})
    del block
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
faults()
print(faults())
"""


def second_allocation_faults(policy: str) -> int:
    done = subprocess.run([sys.executable, "-c", SECOND_ALLOCATION_FAULTS, policy], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return int(done.stdout)


def test_kept_memory_is_reused_without_page_faults():
    if not keep_freed_memory():
        pytest.skip("the C library is not glibc: its allocator has no such policy to set")
    assert second_allocation_faults("default") > PAGES // 2  # the block is mapped afresh: every page faults again
    assert second_allocation_faults("keep") < PAGES // 20
