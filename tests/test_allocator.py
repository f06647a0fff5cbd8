"""matscan.allocator: the command started again with glibc told to reuse freed memory,
measured by the page faults that allocating and freeing a large array again costs (the
kernel's own count)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from matscan.allocator import ENV, POLICY, environment

ROOT = Path(__file__).resolve().parents[1]
FAULTS = """
import resource
import numpy as np
a = np.ones(64 * 2**20 // 8); del a  # the first use faults its pages in either way
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(5):
    a = np.ones(64 * 2**20 // 8); del a
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _plain() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in POLICY and k != ENV}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_the_policy_reuses_freed_memory_without_page_faults(monkeypatch):
    monkeypatch.setattr(os, "environ", _plain())
    env = environment()
    assert env is not None and all(env[k] == v for k, v in POLICY.items())

    def faults(env: dict[str, str]) -> int:
        run = subprocess.run([sys.executable, "-c", FAULTS], env=env, capture_output=True, text=True, check=True)
        return int(run.stdout)

    # five 64 MB arrays allocated and freed: glibc maps each afresh (thousands of faults);
    # under the policy the heap serves them again
    plain, kept = faults(_plain()), faults(env)
    assert plain > 1000 and kept < plain / 20


def test_the_command_runs_as_it_is_where_told_or_already_set(monkeypatch):
    monkeypatch.setattr(os, "environ", {**_plain(), ENV: "system"})
    assert environment() is None
    monkeypatch.setattr(os, "environ", {**_plain(), "MALLOC_MMAP_MAX_": "65536"})  # the user's own setting
    assert environment() is None
