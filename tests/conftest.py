"""Test session set-up and shared fixtures.

The OpenMP wait policy must be set before the first test module imports torch (see
gsbench/__init__.py: two OpenMP runtimes spinning against each other on few cores).
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
os.environ.setdefault("GSBENCH_IMAGE_CACHE", "0")  # tests that use the decoded-image cache turn it on in a tmp folder

import pytest  # noqa: E402
import torch  # noqa: E402

import gsbench  # noqa: E402, F401  (loads libusb-1.0 for open3d where the system has none, before any test imports it)


@pytest.fixture(scope="session")
def tiny_spot(tmp_path_factory):
    """synthetic/spot at 64x48, generated once per session and shared by the method test files."""
    from gsbench.data.synthetic.make import make_scene

    return make_scene("synthetic/spot", out=tmp_path_factory.getbasetemp() / "spot-64x48", res=(64, 48))


@pytest.fixture
def restore_threads():
    """Put torch's thread count back after a test that sets it (``threads=`` in a run config)."""
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A skipped test fails: a missing dependency or a skip must not hide a failure in CI (markers
    deselect the long checks instead, ``-m "not slow"``)."""
    outcome = yield
    report = outcome.get_result()
    if report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        report.outcome = "failed"
        report.longrepr = f"skipped, which this suite does not allow (install what it needs): {reason}"
