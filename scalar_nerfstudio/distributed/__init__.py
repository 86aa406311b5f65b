"""Training the blocks of a trained global run in parallel (``scalar-nerf-train-blocks``).

* :mod:`~scalar_nerfstudio.distributed.executors`: running one block attempt, in a local pool of
  subprocesses or as a Ray task (standard library only at import: Ray workers import it by name);
* :mod:`~scalar_nerfstudio.distributed.run_folders`: the folders: the global run checked, the
  output folder's attempt folders, recorded results (``DONE.json``) and lock (run-folder I/O);
* :mod:`~scalar_nerfstudio.distributed.scheduling`: CPUs and GPUs per block, each attempt's command,
  and the loop that submits, waits for and retries attempts.

The command line itself is ``scalar_nerfstudio/scripts/train_blocks.py``.
"""

COMMAND = "scalar-nerf-train-blocks"


class TrainBlocksError(RuntimeError):
    """A problem with the command's input or resources, reported as one line."""
