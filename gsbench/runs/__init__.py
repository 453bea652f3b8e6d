"""Runs: one run end to end and many of them.

`runner` (load → train → extract → evaluate → record, resumable), `run_lock` (one process at a time in a
run folder), `records` (the JSON record and the environment), `finished_run` (a finished run's folder
loaded back for the diagnostics), `sweep` (grids over methods, scenes, seeds and settings), `executors`
(local processes or Ray), and for Ray across machines with no shared disk (docs/cluster.md) `node_runs` (a run
on a node, its outputs sent back to the driver), `scene_shipping` (its scene on the node) and `ray_nodes` (a
multi-node cluster on one machine). The folder's file names are `gsbench.run_folder.RunFolder`'s.
"""
