"""What the suite needs beyond the package, found in one place: the developer scenes, the tools that
``tools/setup-tests.sh`` installs, and what a test does when one is missing.

A missing prerequisite skips the test and says what is missing. Under ``CI=true`` (``.ci/run`` sets it)
the README's set-up was meant to provide it, so the test fails instead, naming it: a green CI run has
run the browser, video, process-data, Ray and real-photo tests. What no set-up can provide (CUDA,
AVX512-BF16, a C++ compiler) stays a plain skip.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: ``../shared/data`` beside the clone: the developer scenes (CI checks them out there).
SHARED_DATA = REPO.parent / "shared" / "data"
CASTLE = SHARED_DATA / "castle-P30"
FOX = SHARED_DATA / "fox"
FOUNTAIN = SHARED_DATA / "fountain-P11"

SETUP = "tools/setup-tests.sh installs it"
SCENES = "CI checks out ../shared beside the clone"


def in_ci() -> bool:
    """True when CI=true (or 1/yes) is set in the environment."""
    return os.environ.get("CI", "").strip().lower() in ("1", "true", "yes")


def has_tool(name: str) -> bool:
    return shutil.which(name) is not None


def has_module(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def need(what: str, present: bool, *, provided_by: str = SETUP) -> None:
    """Skip the calling test when ``what`` is missing; under CI, fail it, naming what is missing."""
    if present:
        return
    message = f"{what} is missing ({provided_by})"
    if in_ci():
        pytest.fail(f"CI=true and {message}: the README's set-up should have provided it", pytrace=False)
    pytest.skip(message)


def needs(what: str, present: bool, *, provided_by: str = SETUP) -> pytest.MarkDecorator:
    """The marker form of :func:`need`, applied when the test is set up (see conftest's hook)."""
    return pytest.mark.needs(what=what, present=present, provided_by=provided_by)


def apply_needs_markers(item: pytest.Item) -> None:
    """Called from ``pytest_runtest_setup``: :func:`need` for each ``needs`` marker of ``item``."""
    for marker in item.iter_markers(name="needs"):
        need(marker.kwargs["what"], marker.kwargs["present"], provided_by=marker.kwargs["provided_by"])


def need_castle() -> None:
    need(f"castle-P30 ({CASTLE})", CASTLE.is_dir(), provided_by=SCENES)


requires_castle = needs(f"castle-P30 ({CASTLE})", CASTLE.is_dir(), provided_by=SCENES)
requires_pycolmap = needs("pycolmap", has_module("pycolmap"), provided_by="the test extra installs it: pip install -e '.[test]'")
requires_browser = needs("chromium and chromedriver", has_tool("chromium") and has_tool("chromedriver"))
requires_ffmpeg = needs("ffmpeg", has_tool("ffmpeg"))
