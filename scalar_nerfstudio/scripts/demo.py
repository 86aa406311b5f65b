"""``scalar-nerf-demo``: write one of the project's own scenes (if needed) and train SCALAR-NeRF on it.

The scene goes to ``OUTPUT/scenes/NAME`` (beside the runs, outside any source tree). Training shows
a first preview image (``RUN/preview.png``: a held-out view beside its ground truth) after
``--steps-per-preview`` steps, the viewer's address at once, and ends by printing the commands that
view, evaluate and render the run. Everything after ``--`` is passed on to ``ns-train scalar-nerf``,
e.g. ``scalar-nerf-demo -- --pipeline.aabb-scale 1.3 1.3 1.3``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path
from typing import List, Optional, Sequence

from scalar_nerfstudio.runs import run_config_path

#: Library warnings (deprecations inside torch, nerfstudio, websockets; nerfstudio's docstring escapes that
#: Python 3.12 flags when it compiles them) that are not the user's business.
QUIET_WARNINGS = "ignore::FutureWarning,ignore::DeprecationWarning,ignore::UserWarning,ignore::SyntaxWarning"


def quiet_environment(base: Optional[dict] = None) -> dict:
    """``base`` (default: this process's environment) with library warnings silenced."""
    env = dict(os.environ if base is None else base)
    env["PYTHONWARNINGS"] = ",".join(filter(None, [env.get("PYTHONWARNINGS", ""), QUIET_WARNINGS]))
    return env


def write_demo_scene(scene: str, folder: Path, num_images: Optional[int]) -> None:
    """Write the named scene (courtyard: the small default; town: the large one) to ``folder``."""
    if scene == "courtyard":
        from scalar_nerfstudio.scenes.courtyard import write_scene

        write_scene(folder, **({} if num_images is None else {"num_images": num_images}))
    else:
        from scalar_nerfstudio.scenes.town import TownConfig, write_town

        config = TownConfig() if num_images is None else TownConfig(num_images=num_images)
        write_town(folder, config)


def newest_run(output_dir: Path, experiment: str, method: str = "scalar-nerf") -> Optional[Path]:
    """The newest run folder of ``experiment`` under ``output_dir`` (None if there is none)."""
    runs = sorted(path for path in (output_dir / experiment / method).glob("*") if run_config_path(path).is_file())
    return runs[-1] if runs else None


def next_steps(run: Path) -> str:
    """The commands that view, evaluate and render a finished run."""
    config = run_config_path(run)
    return "\n".join([
        f"Done. The run is in {run}; its last preview is {run / 'preview.png'}.",
        "Next:",
        f"  ns-viewer --load-config {config}                       # explore it in the browser",
        f"  ns-eval --load-config {config} --output-path {run / 'eval.json'}   # PSNR / SSIM on held-out views",
        f"  scalar-nerf-eval-fusion --load-config {config}         # every fusion mode against the global model",
        f"  scalar-nerf-render dataset --load-config {config} --split test --output-path {run / 'renders'}",
    ])


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Write the scene to ``--scene-dir`` unless it is there, then run ``ns-train scalar-nerf`` on it."""
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: List[str] = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(prog="scalar-nerf-demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", choices=("courtyard", "town"), default="courtyard",
                        help="courtyard: small, a few minutes (default); town: the large street scene blocks are for")
    parser.add_argument("--scene-dir", type=Path, default=None, help="where the scene is written (default: OUTPUT_DIR/scenes/SCENE)")
    parser.add_argument("--num-images", type=int, default=None, help="images of the scene (default: the scene's own)")
    parser.add_argument("--global-steps", type=int, default=500, help="steps of the global phase")
    parser.add_argument("--num-blocks", type=int, default=0,
                        help="blocks the images are split into (default 0: automatic, as ns-train scalar-nerf decides; "
                             "the courtyard fits one model, so no block is trained unless this is set)")
    parser.add_argument("--block-steps", type=int, default=200, help="steps of each block's phase")
    parser.add_argument("--steps-per-preview", type=int, default=100, help="write RUN/preview.png every this many steps")
    parser.add_argument("--max-num-iterations", type=int, default=0, help="stop after this many steps in all (0: every phase)")
    parser.add_argument("--output-dir", type=Path, default=Path("outputs"), help="nerfstudio output folder")
    args = parser.parse_args(own)
    for name in ("global_steps", "block_steps", "steps_per_preview", "max_num_iterations", "num_blocks"):
        if getattr(args, name) < 0:
            parser.error(f"--{name.replace('_', '-')} must be >= 0, got {getattr(args, name)}")
    scene_dir: Path = args.scene_dir if args.scene_dir is not None else args.output_dir / "scenes" / args.scene
    if not (scene_dir / "transforms.json").is_file():
        print(f"Writing the {args.scene} scene to {scene_dir} ...", flush=True)
        write_demo_scene(args.scene, scene_dir, args.num_images)
    command = [
        sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf",
        "--data", str(scene_dir),
        "--output-dir", str(args.output_dir),
        "--experiment-name", scene_dir.name,
        "--pipeline.global-steps", str(args.global_steps),
        "--pipeline.block-steps", str(args.block_steps),
        "--max-num-iterations", str(args.max_num_iterations),
        "--steps-per-preview", str(args.steps_per_preview),
        "--viewer.quit-on-train-completion", "True",
        *([] if args.num_blocks == 0 else ["--pipeline.num-blocks", str(args.num_blocks)]),
        *extra,
    ]
    blocks = (f"then, if the scene needs K > 1 blocks (automatic K), each block for {args.block_steps} steps" if args.num_blocks == 0
              else f"then {args.num_blocks} blocks for {args.block_steps} steps each")
    print(
        f"Training SCALAR-NeRF: the global model for {args.global_steps} steps, {blocks}.\n"
        f"A preview (held-out view | ground truth) is written every {args.steps_per_preview} steps to "
        f"{args.output_dir / scene_dir.name / 'scalar-nerf' / '<timestamp>' / 'preview.png'}; "
        "the viewer's address is printed below.\nRunning: " + " ".join(command),
        flush=True,
    )
    code = subprocess.call(command, env=quiet_environment())
    run = newest_run(args.output_dir, scene_dir.name)
    if code == 0 and run is not None:
        print(next_steps(run), flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
