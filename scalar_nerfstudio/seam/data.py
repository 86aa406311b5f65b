"""nerfstudio's datasets and datamanager, where scalar-nerf reaches past their public methods
(``nerfstudio/data/datasets/base_dataset.py`` and ``nerfstudio/data/datamanagers/base_datamanager.py`` of
nerfstudio 1.1.5).

What is relied on, each checked by ``tests/test_nerfstudio_seam.py``:

* ``InputDataset`` keeps the parsed outputs it was built from as the private ``_dataparser_outputs``;
* ``VanillaDataManager.setup_train`` / ``setup_eval`` read ``{split}_num_images_to_sample_from`` and
  ``{split}_num_times_to_repeat_images`` from ``self.config`` as they build their image loaders.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace
from typing import Any, Iterator

from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.datasets.base_dataset import InputDataset

__all__ = ["dataparser_outputs", "loader_options"]


def dataparser_outputs(dataset: InputDataset) -> DataparserOutputs:
    """The parsed outputs (image files, metadata, scale) ``dataset`` was built from."""
    return dataset._dataparser_outputs


@contextmanager
def loader_options(datamanager: Any, **options: Any) -> Iterator[None]:
    """While active, ``datamanager.config`` is a copy of its config with ``options`` (e.g.
    ``train_num_images_to_sample_from``), which nerfstudio's ``setup_train`` / ``setup_eval`` read as they
    build their loaders; the config itself is not changed."""
    config = datamanager.config
    datamanager.config = replace(config, **options)
    try:
        yield
    finally:
        datamanager.config = config
