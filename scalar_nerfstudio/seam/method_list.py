"""nerfstudio's list of methods, where it costs every ``ns-*`` command seconds at start
(``nerfstudio/configs/external_methods.py`` of nerfstudio 1.1.5).

nerfstudio builds its method list (``nerfstudio/configs/method_configs.py``) with one
``ExternalMethodDummyTrainerConfig`` for each installable external method (26 of them), and each
one's ``__post_init__`` calls ``inspect.stack()`` only to read the name of the function two frames
up (``get_external_methods``: stay quiet; anything else: offer to install the method).
``inspect.stack`` also reads the source line of every frame, and for a frame without a source file
(importlib's frozen frames: the list is built while ``method_configs`` is imported) it scans all of
``sys.modules``: with torch loaded, seconds of every command's start (docs/results.md, "Command start").

:func:`list_methods_without_reading_sources` gives that module an ``inspect`` whose ``stack()``
returns the same frames with their names and line numbers, without their source lines. What is
relied on, checked by ``tests/test_nerfstudio_seam.py``: the module reads ``inspect`` as a module
global, and ``ExternalMethodDummyTrainerConfig.__post_init__`` uses ``inspect.stack()[2].function``.
"""

from __future__ import annotations

import inspect
import sys
from types import FrameType
from typing import Any, List, Optional

__all__ = ["list_methods_without_reading_sources", "stack_without_sources"]


def stack_without_sources(context: int = 1) -> List[inspect.FrameInfo]:
    """``inspect.stack()`` (the caller's frame first, then the frames that called it) without reading
    any source file: each ``FrameInfo``'s ``code_context`` and ``index`` are None. ``context`` is accepted
    and ignored."""
    del context
    frames: List[inspect.FrameInfo] = []
    frame: Optional[FrameType] = sys._getframe(1)
    while frame is not None:
        frames.append(inspect.FrameInfo(frame, frame.f_code.co_filename, frame.f_lineno, frame.f_code.co_name, None, None))
        frame = frame.f_back
    return frames


class _InspectWithoutSources:
    """The ``inspect`` module, but for ``stack``."""

    stack = staticmethod(stack_without_sources)

    def __getattr__(self, name: str) -> Any:
        return getattr(inspect, name)


def list_methods_without_reading_sources() -> None:
    """Make nerfstudio's method list skip the source lines of ``inspect.stack`` (see the module's text).

    Called when nerfstudio loads this package's methods (its entry points), which nerfstudio does before
    it lists the external methods. Does nothing where nerfstudio's module is not as described."""
    from nerfstudio.configs import external_methods

    if getattr(external_methods, "inspect", None) is inspect:
        external_methods.inspect = _InspectWithoutSources()  # type: ignore[assignment]
