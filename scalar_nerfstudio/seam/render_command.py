"""nerfstudio's ``ns-render`` commands (``nerfstudio/scripts/render.py`` of nerfstudio 1.1.5), given a say in
the runs they load.

``ns-render``'s options are fixed by nerfstudio, with no hook for a plugin to add one. Its commands
(``RenderCameraPath``, ``RenderInterpolated``, ``SpiralRender``, ``DatasetRender``) load the run in their
``main`` with the ``eval_setup`` name of their own module; :func:`after_each_load` replaces that name
while it is active. Checked by ``tests/test_nerfstudio_seam.py``.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterator, Tuple

from nerfstudio.scripts import render as ns_render

__all__ = ["after_each_load"]


@contextlib.contextmanager
def after_each_load(change: Callable[[Any, Any], None]) -> Iterator[None]:
    """While active, every run that ``ns-render``'s commands load is handed to ``change(config, pipeline)``
    before they render it (nerfstudio's ``eval_setup`` returns it to them then)."""
    original = ns_render.eval_setup

    def eval_setup_then_change(*args: Any, **kwargs: Any) -> Tuple[Any, Any, Any, Any]:
        config, pipeline, checkpoint, step = original(*args, **kwargs)
        change(config, pipeline)
        return config, pipeline, checkpoint, step

    ns_render.eval_setup = eval_setup_then_change
    try:
        yield
    finally:
        ns_render.eval_setup = original
