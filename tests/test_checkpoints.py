"""Checkpoints are atomic; a resumed run continues at the saved step with the same state (a run killed
with SIGKILL and resumed from the command line: test_scale.py)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch
import yaml
from conftest import TRAIN_STEPS, free_port
from prerequisites import requires_castle

from scalar_nerfstudio.atomic_io import PARTIAL_SUFFIX, atomic_torch_save
from scalar_nerfstudio.runs import latest_checkpoint_step


def test_failed_write_keeps_previous_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    checkpoint = tmp_path / "run" / "nerfstudio_models" / "step-000000010.ckpt"
    checkpoint.parent.mkdir(parents=True)
    atomic_torch_save({"step": 10, "w": torch.ones(3)}, checkpoint)

    def crash(obj, handle, *args, **kwargs):
        handle.write(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", crash)
    with pytest.raises(OSError):
        atomic_torch_save({"step": 10, "w": torch.zeros(3)}, checkpoint)
    assert torch.load(checkpoint)["w"].tolist() == [1.0, 1.0, 1.0]
    assert os.listdir(checkpoint.parent) == ["step-000000010.ckpt"]


def test_process_killed_while_writing_leaves_no_checkpoint(tmp_path: Path) -> None:
    checkpoint = tmp_path / "run" / "nerfstudio_models" / "step-000000001.ckpt"
    checkpoint.parent.mkdir(parents=True)
    writer = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import torch
        from pathlib import Path
        from scalar_nerfstudio.atomic_io import atomic_torch_save
        atomic_torch_save({{"big": torch.ones(400_000_000, dtype=torch.uint8)}}, Path({str(checkpoint)!r}))
        """)])
    partial = checkpoint.parent.parent / f".{checkpoint.stem}{PARTIAL_SUFFIX}"
    deadline = time.time() + 60
    while not (partial.exists() and partial.stat().st_size > 0) and time.time() < deadline and writer.poll() is None:
        time.sleep(0.01)
    writer.send_signal(signal.SIGKILL)
    writer.wait()
    assert partial.exists(), "the writer finished before it could be killed mid-write"
    assert not checkpoint.exists()
    assert latest_checkpoint_step(checkpoint.parent) is None


def _copy_run(run: Path, destination: Path) -> Path:
    """Copy a run folder to ``destination`` (keeping OUTPUT/EXPERIMENT/METHOD/TIMESTAMP)."""
    copied = destination / run.parent.parent.name / run.parent.name / run.name
    shutil.copytree(run, copied)
    return copied


@pytest.mark.slow
@requires_castle
def test_resume_continues_at_saved_step_with_same_state(trained_castle_run: Path, tmp_path: Path) -> None:
    run = _copy_run(trained_castle_run, tmp_path)
    config = yaml.load((run / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = tmp_path
    config.load_dir = run / "nerfstudio_models"
    config.max_num_iterations = TRAIN_STEPS + 5
    config.viewer.websocket_port = free_port()
    config.viewer.quit_on_train_completion = True
    saved = torch.load(run / "nerfstudio_models" / f"step-{TRAIN_STEPS - 1:09d}.ckpt", map_location="cpu")

    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    assert trainer._start_step == TRAIN_STEPS
    for name, value in trainer.pipeline.state_dict().items():
        assert torch.equal(value.cpu(), saved["pipeline"][name]), name
    encoder_state = trainer.optimizers.optimizers["encoder"].state_dict()["state"][0]
    assert torch.equal(encoder_state["exp_avg"].cpu(), saved["optimizers"]["encoder"]["state"][0]["exp_avg"])
    trainer.train()
    assert latest_checkpoint_step(run / "nerfstudio_models") == TRAIN_STEPS + 4


@pytest.mark.slow  # trains
def test_finished_phases_drop_their_optimizer_moments(scene: Path, tmp_path: Path) -> None:
    """Once a phase ends its groups never train again: their Adam moments leave memory and the checkpoints."""
    from conftest import tiny_trainer

    from scalar_nerfstudio.runs import checkpoint_name

    trainer = tiny_trainer(scene, tmp_path, global_steps=12, block_steps=6)
    trainer.train()
    optimizers = trainer.optimizers.optimizers
    assert optimizers["encoder"].state == {} and optimizers["block0.encoder"].state == {}  # the global phase and block 0 are done
    assert optimizers["block1.encoder"].state  # the last phase keeps its moments (a resume could continue it)
    last = latest_checkpoint_step(trainer.checkpoint_dir)
    saved = torch.load(trainer.checkpoint_dir / checkpoint_name(last), map_location="cpu", weights_only=False)["optimizers"]
    assert saved["encoder"]["state"] == {} and saved["block0.decoder"]["state"] == {} and saved["block1.encoder"]["state"]
