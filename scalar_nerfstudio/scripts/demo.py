"""``scalar-nerf-demo``: generate the built-in courtyard scene (if needed) and train on it.

Everything after ``--`` is passed on to ``ns-train scalar-nerf``, e.g.
``scalar-nerf-demo -- --pipeline.aabb-scale 1.3 1.3 1.3``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path
from typing import List, Optional

from scalar_nerfstudio.data.synthetic_scene import write_scene


def main(argv: Optional[List[str]] = None) -> int:
    """Write the scene to ``--scene-dir`` unless it is there, then run ``ns-train scalar-nerf`` on it."""
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(prog="scalar-nerf-demo", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene-dir", type=Path, default=Path("scalar-nerf-demo-scene"), help="where the scene is written")
    parser.add_argument("--global-steps", type=int, default=500, help="steps of the global phase")
    parser.add_argument("--num-blocks", type=int, default=2, help="blocks the images are split into")
    parser.add_argument("--block-steps", type=int, default=250, help="steps of each block's phase")
    parser.add_argument("--max-num-iterations", type=int, default=0, help="stop after this many steps in all (0: every phase)")
    parser.add_argument("--output-dir", type=Path, default=Path("outputs"), help="nerfstudio output folder")
    args = parser.parse_args(own)
    if not (args.scene_dir / "transforms.json").is_file():
        print(f"Writing the built-in courtyard scene to {args.scene_dir} ...", flush=True)
        write_scene(args.scene_dir)
    command = [
        sys.executable, "-m", "nerfstudio.scripts.train", "scalar-nerf",
        "--data", str(args.scene_dir),
        "--output-dir", str(args.output_dir),
        "--pipeline.global-steps", str(args.global_steps),
        "--pipeline.num-blocks", str(args.num_blocks),
        "--pipeline.block-steps", str(args.block_steps),
        "--max-num-iterations", str(args.max_num_iterations),
        "--viewer.quit-on-train-completion", "True",
        *extra,
    ]
    print("Running:", " ".join(command), flush=True)
    return subprocess.call(command)


if __name__ == "__main__":
    sys.exit(main())
