"""Configuration: what a run is, before anything runs.

`files` (the shipped ``configs/`` folder, YAML reading, "did you mean" hints), `suites` (named lists of
scenes and seeds), `run_config` (the `RunConfig` dataclasses, the layering of YAML files and ``--set``
overrides, the run id) and `checks` (what can be checked of a configuration before a scene loads).
"""
