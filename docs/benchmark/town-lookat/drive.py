"""One-off probe driver: the benchmark runner, with each block's datamanager given that block's pixel masks."""
import json, sys
from dataclasses import replace
from pathlib import Path
import scalar_nerfstudio.data.datamanager as dm
from scalar_nerfstudio.benchmarking import runner

here = Path(__file__).parent
plan = json.load(open(here / "plan" / "blocks.json"))
masks = json.load(open(here / "mask_paths.json"))
by_subset = {tuple(b["image_indices"]): b["index"] for b in plan["blocks"]}
original = dm.subset_dataparser_outputs
USE_MASKS = "--no-masks" not in sys.argv

def with_masks(outputs, image_indices):
    k = by_subset.get(tuple(image_indices))
    if k is not None and USE_MASKS:
        outputs = replace(outputs, mask_filenames=[Path(p) for p in masks[str(k)]])
        print(f"PROBE: block {k}: {len(image_indices)} images with their masks", flush=True)
    return original(outputs, image_indices)

dm.subset_dataparser_outputs = with_masks
runner.main()
