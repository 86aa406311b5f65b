"""The fused AVX2 decoder's two MLPs, forward and backward, 40 times over 150k samples: the load for a profile
of the kernels (which of their register blocks the time goes to).

    perf record -g python docs/benchmark/avx2-decoder/perf_mlps.py && perf report --no-children --sort symbol
"""

import torch
from torch import nn

from scalar_nerfstudio.engine.allocator import keep_freed_memory
from scalar_nerfstudio.fields.fused_mlp_float32 import fused_mlp_float32

keep_freed_memory()  # malloc as training sets it
torch.set_num_threads(2)
points = 150_000
density = nn.Sequential(nn.Linear(64, 64), nn.ReLU(), nn.Linear(64, 16))  # the decoder's layer sizes
colour = nn.Sequential(nn.Linear(39, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(), nn.Linear(64, 3))
features = torch.randn(points, 64)  # the encoder's features: no gradient, as in the decoder benchmark
colour_in = torch.randn(points, 39, requires_grad=True)
for _ in range(40):
    (fused_mlp_float32(density, features, "avx2").sum() + fused_mlp_float32(colour, colour_in, "avx2").sum()).backward()
