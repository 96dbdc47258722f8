"""The test session's memory watchdog (fixtures/memory_alarm.py) names the test and its stacks, once."""

from __future__ import annotations

from pathlib import Path

import pytest

from fixtures.memory_alarm import STATUS, MemoryAlarm, resident_gib

pytestmark = pytest.mark.skipif(not STATUS.is_file(), reason="needs Linux /proc")


def test_the_alarm_names_the_test_and_dumps_the_stacks_once():
    said = []
    alarm = MemoryAlarm(threshold_gib=1e-6, write=said.append)
    alarm.current = "tests/x.py::test_big"
    assert alarm.check() and not alarm.check()
    assert len(said) == 1 and "during tests/x.py::test_big" in said[0] and "GiB" in said[0]
    assert "test_the_alarm_names_the_test_and_dumps_the_stacks_once" in said[0]  # this thread's stack


def test_the_alarm_stays_quiet_under_its_threshold():
    said = []
    alarm = MemoryAlarm(threshold_gib=1e6, write=said.append)
    assert not alarm.check() and said == []
    assert 0 < resident_gib() < 1e6


def test_the_threshold_comes_from_the_environment(monkeypatch):
    from fixtures.memory_alarm import from_environment

    monkeypatch.setenv("PILIGHT_TEST_RSS_ALARM_GIB", "0")
    assert from_environment() is None
    monkeypatch.setenv("PILIGHT_TEST_RSS_ALARM_GIB", "3.5")
    assert from_environment().threshold_gib == 3.5
    assert Path("/proc/self/status") == STATUS
