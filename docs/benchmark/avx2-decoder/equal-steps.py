"""The AVX2 decoder path against torch's float32 path at equal steps: castle-P30 at downscale 4,
400 steps each, the held-out PSNR as ns-eval computes it. Run from anywhere:

    python docs/benchmark/avx2-decoder/equal-steps.py [OUTPUT_DIR]
"""
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))
from conftest import CASTLE, ns_train_command, run_dirs  # noqa: E402
from quality import eval_renders, load_pipeline  # noqa: E402

output = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="equal-steps-"))
for kernel in ["torch", "avx2"]:
    out = output / kernel
    extra = ["--pipeline.model.field.cpu-decoder-kernel", kernel, "--pipeline.model.field.decoder-precision", "float32"]
    start = time.time()
    result = subprocess.run(ns_train_command(CASTLE, out, "--max-num-iterations", "400", "--steps-per-save", "400", *extra,
                                             "nerfstudio-data", "--downscale-factor", "4"), capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-3000:]
    (run,) = run_dirs(out)
    metrics, _ = eval_renders(load_pipeline(run))
    print(kernel, f"{time.time() - start:.0f} s", round(metrics["psnr"], 3), flush=True)
