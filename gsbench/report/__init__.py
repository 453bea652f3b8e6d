"""``gsbench report``: leaderboards, cost and training time against error, and sweep ablations from run records.

`build.write_report` is the entry point (docs/report.md). The modules, in data-flow order: `records_file` (a
board's records in one file), `collect` (read records and sweep manifests, label configurations), `metrics`
(direction/unit of a metric, the ranking metric of a dataset, the papers' reported numbers), `aggregate`
(rows × scenes, mean ± std over seeds), `joins` (which rows share a curve of error against time), `anytime` (the
runs' points as curves, their values at time budgets), `pareto` (non-dominated cost/error points), `tables` (cells,
Markdown), `views` (the tables of boards), `anytime_tables` (the tables of error against time), `run_tables` (the
tables of single runs), `leaderboard_csv`, `plots` (matplotlib PNGs), `surfaces` (pictures of the meshes), `png`
(small PNGs that say what they show) and `html` (the page).
"""
