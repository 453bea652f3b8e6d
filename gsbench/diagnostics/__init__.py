"""Diagnostics of a finished run: `depth_check` (its fused depth against the exact depth, ``gsbench
depth``), `gaussian_placement` (where its Gaussians are, ``gsbench gaussians``) and `text_table` (their
aligned text tables)."""
