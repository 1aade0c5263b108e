"""The numerical stress checks of cli/bench/stress.py, what `noisenerf bench --stress` runs, as tests: the
fast subset of their cases, or every case with NOISENERF_STRESS=full."""

from __future__ import annotations

import os

import pytest

from noisenerf.cli.bench.stress import case_name, stress_cases, stress_scene

FULL = os.environ.get("NOISENERF_STRESS") == "full"


@pytest.fixture(scope="module")
def stressed(tmp_path_factory):
    return stress_scene(tmp_path_factory.mktemp("stress"))


@pytest.mark.parametrize("check, case", [pytest.param(check, case, id=case_name(check, case))
                                         for check, case in stress_cases(FULL)])
def test_stress(stressed, check, case):
    check.run(stressed, *case)
