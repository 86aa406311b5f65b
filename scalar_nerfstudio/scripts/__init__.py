"""The ``scalar-nerf-*`` command lines.

Importing this package is the first thing each command does (its console script imports
``scalar_nerfstudio.scripts.<command>``), so the one process-wide setting every command shares is made
here, before nerfstudio is imported: the deprecation warnings that torch, nerfstudio and their
dependencies print on import are not the user's business, and would bury a command's one-line error.
"""

import warnings

for _category in (FutureWarning, DeprecationWarning):
    warnings.filterwarnings("ignore", category=_category, module=r"(nerfstudio|torch|tyro|websockets|viser|pkg_resources)(\.|$)")
