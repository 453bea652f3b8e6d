"""Test session set-up: the OpenMP wait policy must be set before the first test module imports torch
(see gsbench/__init__.py: two OpenMP runtimes spinning against each other on few cores)."""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
