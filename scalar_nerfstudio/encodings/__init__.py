"""Encodings: the multi-resolution hash grid (C++/OpenMP on CPU, a CUDA kernel on CUDA, vectorised torch elsewhere)."""

from scalar_nerfstudio.encodings._cpp import (
    extension_available as cpp_extension_available,
    extension_error as cpp_extension_error,
)
from scalar_nerfstudio.encodings.hash_grid import (
    GridLayout,
    HashGridEncoding,
    grid_resolutions,
    hash_encoding_cpp,
    hash_encoding_cuda,
    hash_encoding_torch,
    level_corners,
    level_row_counts,
)

__all__ = [
    "GridLayout",
    "HashGridEncoding",
    "cpp_extension_available",
    "cpp_extension_error",
    "grid_resolutions",
    "hash_encoding_cpp",
    "hash_encoding_cuda",
    "hash_encoding_torch",
    "level_corners",
    "level_row_counts",
]
