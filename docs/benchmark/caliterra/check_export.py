"""Does ``ns-export pointcloud --save-world-frame True`` of a run lie on the capture's own sparse SfM
points (``SCENE/sparse_pc.ply``, written by scalar-nerf-process-data in the same GPS frame, metres)?

Prints, in metres: each cloud's extent, and the median and 90th percentile of the distance from each
exported point to its nearest sparse point and from each sparse point to its nearest exported one.
Exits 1 when the median exported-to-sparse distance exceeds ``--max-median`` times the sparse
cloud's extent (default 2 %), i.e. when the export is not in the capture's frame and scale.

    python docs/benchmark/caliterra/check_export.py --scene SCENE --points export/point_cloud.ply
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from plyfile import PlyData
from scipy.spatial import cKDTree


def read_points(path: Path) -> np.ndarray:
    """[N, 3] float64 vertex positions of a .ply file."""
    vertex = PlyData.read(str(path))["vertex"]
    return np.stack([np.asarray(vertex[axis], dtype=np.float64) for axis in "xyz"], axis=1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--points", type=Path, required=True, help="the exported point cloud (.ply)")
    parser.add_argument("--max-median", type=float, default=0.02, help="largest median distance, as a fraction of the sparse extent")
    args = parser.parse_args()
    sparse, exported = read_points(args.scene / "sparse_pc.ply"), read_points(args.points)
    extent = float(np.linalg.norm(np.percentile(sparse, 99, axis=0) - np.percentile(sparse, 1, axis=0)))
    to_sparse, _ = cKDTree(sparse).query(exported)
    to_export, _ = cKDTree(exported).query(sparse)
    for name, cloud in (("sparse SfM points", sparse), ("exported points", exported)):
        low, high = np.percentile(cloud, 1, axis=0), np.percentile(cloud, 99, axis=0)
        print(f"{name}: {len(cloud)}, 1-99 % box from {np.round(low, 1).tolist()} to {np.round(high, 1).tolist()} m")
    print(f"sparse extent (1-99 % box diagonal): {extent:.1f} m")
    print(f"exported -> nearest sparse point: median {np.median(to_sparse):.3f} m, 90 % {np.percentile(to_sparse, 90):.3f} m")
    print(f"sparse -> nearest exported point: median {np.median(to_export):.3f} m, 90 % {np.percentile(to_export, 90):.3f} m")
    ratio = float(np.median(to_sparse)) / extent
    print(f"median exported -> sparse distance: {100 * ratio:.2f} % of the extent (limit {100 * args.max_median:.0f} %)")
    return 0 if ratio <= args.max_median else 1


if __name__ == "__main__":
    sys.exit(main())
