"""Mesh clean-up shared by the extractors (2DGS ``post_process_mesh``, methods-3dgs-2dgs-sugar.md §2.9).

- `keep_largest_clusters`: keep the triangles of the ``n`` largest connected components; the size
  cut-off is max(size of the n-th largest, ``min_triangles`` = 50), as 2DGS. ``n <= 0`` keeps all.
- `clean`: remove degenerate triangles and unreferenced vertices.
- `to_trimesh`: open3d ``TriangleMesh`` -> ``trimesh.Trimesh`` (vertex colours kept).
"""

from __future__ import annotations

import numpy as np

MIN_CLUSTER_TRIANGLES = 50


def clean(mesh):
    """Remove degenerate triangles and unreferenced vertices (in place); returns ``mesh``."""
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    return mesh


def keep_largest_clusters(mesh, n: int, min_triangles: int = MIN_CLUSTER_TRIANGLES):
    """Drop triangles of connected components smaller than max(n-th largest size, ``min_triangles``)."""
    if n <= 0 or len(mesh.triangles) == 0:
        return clean(mesh)
    labels, sizes, _ = mesh.cluster_connected_triangles()
    labels, sizes = np.asarray(labels), np.asarray(sizes)
    ranked = np.sort(sizes)[::-1]
    cutoff = max(int(ranked[min(n, len(ranked)) - 1]), min_triangles)
    mesh.remove_triangles_by_mask(sizes[labels] < cutoff)
    return clean(mesh)


def to_trimesh(mesh):
    """An open3d ``TriangleMesh`` as a ``trimesh.Trimesh`` (no processing; colours as uint8 RGBA)."""
    import trimesh  # noqa: PLC0415

    colors = None
    if mesh.has_vertex_colors():
        rgb = np.clip(np.asarray(mesh.vertex_colors) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        colors = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], 1)
    return trimesh.Trimesh(vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.triangles),
                           vertex_colors=colors, process=False)
