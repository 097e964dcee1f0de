"""The satsweep command's heap policy (satsweep.heap), checked in child processes so that the
test process keeps glibc's defaults."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from satsweep import heap

_PROBE = "from satsweep.heap import keep_freed_memory; print(keep_freed_memory())"


def _probe(switch: str | None) -> str:
    env = dict(os.environ)
    env.pop(heap.ENV_SWITCH, None)
    if switch is not None:
        env[heap.ENV_SWITCH] = switch
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                         check=True)
    return out.stdout.strip()


@pytest.mark.skipif(not heap._is_glibc(), reason="the policy applies to glibc only")
def test_policy_applies_on_glibc_and_can_be_turned_off():
    assert _probe(None) == "True"
    assert _probe("1") == "True"
    assert _probe("0") == "False"


def test_python_m_satsweep_goes_through_console_main():
    """``python -m satsweep`` starts the command the way the console script does."""
    out = subprocess.run([sys.executable, "-m", "satsweep", "config"], capture_output=True,
                         text=True, check=True)
    assert "[sweep]" in out.stdout
