"""``import arraysel`` makes idle OpenMP threads sleep (issue 78) unless the user chose a policy."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = "import os, arraysel; print(os.environ.get('OMP_WAIT_POLICY'))"


@pytest.mark.parametrize("given, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE"), ("passive", "passive")])
def test_wait_policy(given, expected):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given is not None:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, stdout=subprocess.PIPE, text=True, check=True)
    assert out.stdout.strip() == expected
