"""Evaluators: one module per metric family (installed as ``gsbench.evaluators``).

CLI entry points live in `gsbench.evaluators.api`: ``evaluate_mesh_file``, ``format_table``,
``get_evaluator`` (backed by `gsbench.registry.EVALUATORS`). Importing this package imports
nothing heavy.
"""
