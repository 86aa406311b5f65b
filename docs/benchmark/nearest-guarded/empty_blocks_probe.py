"""A probe (docs/notebook/defaults.md, "Fusion: nearest-guarded"): a trained run with some of its blocks made empty (their
density scaled down by e^-100, so they render the background colour everywhere, as the paper's fresh
blocks did before the fix of 2026-11-27), fused by `nearest` and by `nearest-guarded`.

python docs/benchmark/nearest-guarded/empty_blocks_probe.py RUN/config.yml OUT.json [BLOCK ...]   (no BLOCK: every block)
"""

import json
import sys
from pathlib import Path

from nerfstudio.utils.eval_utils import eval_setup

from scalar_nerfstudio.fusion_eval import evaluate_fusion_modes, markdown_table

config, output = Path(sys.argv[1]), Path(sys.argv[2])
_, pipeline, _, _ = eval_setup(config, test_mode="test")
model = pipeline.model
emptied = [int(b) for b in sys.argv[3:]] or list(model.started_block_ids())
for block in emptied:
    model.blocks[str(block)].field.decoder.density_bias = -100.0
table = evaluate_fusion_modes(pipeline, ["nearest", "nearest-guarded", "global-only"], measure_selection=False)
table["emptied_blocks"] = {"blocks": emptied}
output.write_text(json.dumps(table, indent=2))
print(f"emptied blocks {emptied} of {config}")
print(markdown_table({k: v for k, v in table.items() if k != "emptied_blocks"}))
