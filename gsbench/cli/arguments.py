"""Argument types and help texts that more than one command shares."""

from __future__ import annotations

import argparse

GT_HELP = ("folder holding the ground truth when it is not beside the scene: DTU's Points/ and ObsMask/ "
           "(the official SampleSet), or a TnT scene's .ply, .json, _trans.txt and _COLMAP_SfM.log")
RUN_DIR_HELP = "the run's folder (<out>/<dataset>/<scene>/<method>/<run_id>)"
THREADS_HELP = "OpenMP / torch threads (0 = all)"


def threads_count(text: str) -> int:
    """``--threads``: an integer >= 0 (0: every core), else argparse's usage error."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0 (0: every core), got {text!r}")
    return value
