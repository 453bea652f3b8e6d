"""Evaluators: one module per metric family (installed as ``gsbench.evaluators``).

CLI entry points live in `gsbench.evaluators.api` (``evaluate_mesh_file``, ``format_table``,
``default_evaluators``); `gsbench.evaluators.resolve` decides which evaluators a run computes and
looks them up (``get_evaluator``, backed by `gsbench.registry.EVALUATORS`: each built-in declared by
``configs/evaluators/<name>.yaml``). Importing this package imports nothing heavy.
"""
