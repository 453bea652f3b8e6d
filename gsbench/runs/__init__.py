"""Runs: one run end to end and many of them.

`runner` (load → train → extract → evaluate → record, resumable), `run_lock` (one process at a time in a
run folder), `records` (the JSON record and the environment), `finished_run` (a finished run's folder
loaded back for the diagnostics), `sweep` (grids over methods, scenes, seeds and settings) and `executors`
(local processes or Ray). The folder's file names are `gsbench.run_folder.RunFolder`'s.
"""
