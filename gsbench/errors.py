"""Error types. Every message says what was found, what was expected and how to fix it.

The CLI prints a `GsbenchError` as one line without a traceback (``--debug`` shows it) and exits 2.
"""


class GsbenchError(Exception):
    """Base class of all errors gsbench reports to a user."""


class ConfigError(GsbenchError):
    """A config file, key or value is wrong."""


class DataError(GsbenchError):
    """A scene folder, camera, image, mask or ground-truth file is missing or malformed."""


class GroundTruthRead(GsbenchError):
    """A method read the scene's ground truth, which only the evaluators may read (`gsbench.data.method_scene`)."""


class RegistryError(GsbenchError):
    """An unknown method, evaluator or scene name."""


class NumericalError(GsbenchError):
    """A non-finite or otherwise invalid numerical input (e.g. NaN in a Gaussian parameter)."""


class EvaluationError(GsbenchError):
    """A mesh or point cloud cannot be evaluated (empty, NaN, wrong units, missing GT file)."""


class CheckpointError(GsbenchError):
    """A checkpoint that cannot be read back as data (damaged, or holding objects to unpickle)."""


class BuildError(GsbenchError):
    """The C++ rasterizer extension could not be compiled or loaded."""


class Interrupted(BaseException):
    """SIGTERM received during a run: it stops like a Ctrl-C (status ``interrupted``, resumable)."""


def missing_dependency(package: str, fix: str) -> GsbenchError:
    """An ImportError turned into a message that names the fix."""
    return GsbenchError(f"the Python package '{package}' could not be imported; fix: {fix}")


def import_open3d():
    """Import open3d lazily; a missing system library (libusb-1.0 on Debian) becomes a clear error."""
    try:
        import open3d  # noqa: PLC0415
    except ImportError as exc:  # pragma: no cover - depends on the machine
        hint = "pip install open3d"
        if "libusb" in str(exc):
            hint = (f"open3d needs libusb-1.0 ({exc}): pip install libusb-package (a gsbench dependency on Linux, "
                    "loaded when gsbench is imported), or the system package (Debian/Ubuntu: apt-get install libusb-1.0-0)")
        elif "libGL" in str(exc) or ".so" in str(exc):
            hint = f"install the missing system library ({exc})"
        raise missing_dependency("open3d", hint) from exc
    return open3d


def one_line(text, limit: int = 300) -> str:
    """``text`` with runs of whitespace (newlines included) collapsed, cut to ``limit`` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."
