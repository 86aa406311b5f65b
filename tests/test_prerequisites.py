"""A missing prerequisite skips a test on a developer's machine and fails it under CI=true."""

from __future__ import annotations

import pytest
from prerequisites import apply_needs_markers, need, needs


def _outcome(call, *args, **kwargs) -> BaseException | None:
    """What ``call`` raised (a skip, a failure), caught here so that a wrong outcome fails this test."""
    try:
        call(*args, **kwargs)
    except BaseException as raised:  # noqa: BLE001 - pytest's outcomes derive from BaseException
        return raised
    return None


def test_a_missing_prerequisite_skips_outside_ci_and_fails_under_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CI", raising=False)
    skipped = _outcome(need, "ffmpeg", False)
    assert isinstance(skipped, pytest.skip.Exception) and "ffmpeg is missing" in str(skipped)
    for value in ("true", "1", "TRUE"):
        monkeypatch.setenv("CI", value)
        failed = _outcome(need, "ffmpeg", False)
        assert isinstance(failed, pytest.fail.Exception) and "CI=true and ffmpeg is missing" in str(failed), failed
        assert _outcome(need, "ffmpeg", True) is None  # present: nothing happens


def test_ci_false_means_not_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CI", "false")
    assert isinstance(_outcome(need, "chromium", False), pytest.skip.Exception)


class _Item:
    """What apply_needs_markers reads of a pytest item."""

    def __init__(self, *marks: pytest.MarkDecorator) -> None:
        self.marks = [m.mark for m in marks]

    def iter_markers(self, name: str):
        return [m for m in self.marks if m.name == name]


def test_the_marker_form_checks_every_needs_marker(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CI", "true")
    assert _outcome(apply_needs_markers, _Item(needs("python", True))) is None
    failed = _outcome(apply_needs_markers, _Item(needs("python", True), needs("a tool nobody has", False, provided_by="nothing")))
    assert isinstance(failed, pytest.fail.Exception) and "a tool nobody has is missing" in str(failed), failed
