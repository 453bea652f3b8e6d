"""A run on a Ray node that shares no disk with the driver (docs/cluster.md §1-§3).

The task (`run_on_node`) runs the run in the node's own run folder, ``<GSBENCH_NODE_RUNS>/<dataset>/<scene>/<method>/
<run_id>`` (`node_run_root`), and returns its outputs through Ray (`NodeResult`): every file of the run folder but the
checkpoints and the lock (`collect_outputs`: the record, the mesh, ``eval.json``, ``stages.json``, the training log,
``config.yaml`` and the points, what the report and its pictures read), at most `OUTPUTS_CAP_BYTES` in all. The
driver writes them into its own run folder (`land_outputs`), each file atomically and the record last, with the
node's folder replaced by the driver's in the text files, so the records of a Ray sweep are a local sweep's; the
record's ``environment.ray`` says which node ran it, after how many attempts (the driver counts them).

The checkpoints stay on the node. A run sent again (a retry after a node died, a driver restarted) resumes from its
checkpoint when it lands on the node that holds its folder, and starts again elsewhere.

The scene reaches the node by `gsbench.runs.scene_shipping` (`scene_on_node`).
"""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass
from pathlib import Path

from gsbench.atomic import atomic_path
from gsbench.config.run_config import RunConfig
from gsbench.errors import GsbenchError
from gsbench.run_folder import RunFolder
from gsbench.runs.records import write_json_atomic
from gsbench.runs.runner import run_dir
from gsbench.runs.scene_shipping import SceneTicket, check_scene_hash, scene_on_node
from gsbench.switches import NODE_RUNS

# The most a run may send back to the driver: Ray holds it in the object store of both nodes until it is written.
OUTPUTS_CAP_BYTES = 2 << 30
# Files that stay on the node: the checkpoints (large; they resume the run there) and the lock.
NODE_ONLY_SUFFIXES = (".pt",)
NODE_ONLY_NAMES = (RunFolder.LOCK,)
# Files whose text names the run folder (config.yaml's out, the record's and eval.json's mesh paths).
TEXT_SUFFIXES = (".json", ".jsonl", ".yaml")


class OutputsTooLarge(GsbenchError):
    """A run's outputs are more than `OUTPUTS_CAP_BYTES`."""


@dataclass
class NodeResult:
    """What the task sends back: ``value`` (the run function's return), ``files`` (path in the run folder -> bytes),
    the node's run root (``node_root``), its Ray ``node_id``, the ``attempt`` (1 for the first) and the content hash
    of the scene as the node read it (None when the scene is read in place unchecked, ``scene_paths: shared``)."""

    value: object
    files: dict
    node_root: str
    node_id: str
    attempt: int
    scene_hash: str | None


def node_run_root() -> Path:
    """This node's run folder root, ``$GSBENCH_NODE_RUNS`` (default ``~/.cache/gsbench/node-runs``)."""
    return Path(NODE_RUNS.value()).expanduser().resolve()


def run_on_node(fn, cfg: RunConfig, ticket: SceneTicket, attempt: int) -> NodeResult:
    """The Ray task of a run: ``fn(cfg)`` with ``cfg.out`` set to this node's run root, its scene placed by
    ``ticket`` (`scene_on_node`), and its outputs collected (`collect_outputs`). ``attempt``: 1 for the first start,
    counted by the driver (`gsbench.runs.executors.RayExecutor`)."""
    import ray  # noqa: PLC0415  (inside a Ray task: installed)

    root = node_run_root()
    on_node = copy.deepcopy(cfg)
    on_node.out = str(root)
    with scene_on_node(ticket, ray.get) as scene_hash:
        value = fn(on_node)
    return NodeResult(value, collect_outputs(run_dir(on_node)), str(root), ray.get_runtime_context().get_node_id(),
                      attempt, scene_hash)


def collect_outputs(folder: Path) -> dict:
    """``{path relative to folder: bytes}`` of every file of the run folder ``folder`` but the checkpoints and the
    lock; `OutputsTooLarge` above `OUTPUTS_CAP_BYTES`."""
    files = sorted(p for p in Path(folder).rglob("*") if p.is_file() and p.suffix not in NODE_ONLY_SUFFIXES
                   and p.name not in NODE_ONLY_NAMES and not p.name.startswith("."))
    total = sum(p.stat().st_size for p in files)
    if total > OUTPUTS_CAP_BYTES:
        raise OutputsTooLarge(f"{folder}: the run's outputs are {total / 2**30:.2f} GiB, more than the "
                              f"{OUTPUTS_CAP_BYTES / 2**30:g} GiB a Ray task sends back to the driver "
                              "(docs/cluster.md §1); fix: a smaller mesh (mesh.voxel_size) or fewer eval.points, or "
                              "run the sweep with --executor local on a machine holding --out")
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in files}


def land_outputs(result: NodeResult, cfg: RunConfig, expected_scene_hash: str | None):
    """Write ``result``'s files into ``cfg``'s run folder (at the driver) and return its value: the node's run root
    replaced by ``cfg.out`` in the text files, each file atomic, the record last with ``environment.ray`` added.
    A scene the node read with another content than the driver's is a GsbenchError (`check_scene_hash`), before
    anything is written."""
    check_scene_hash(cfg.scene, expected_scene_hash, result.scene_hash, result.node_id)
    folder = run_dir(cfg)
    record_name = RunFolder.RECORD
    for name, data in sorted(result.files.items(), key=lambda item: item[0] == record_name):
        if Path(name).suffix in TEXT_SUFFIXES:
            data = data.decode().replace(result.node_root, str(Path(cfg.out).resolve())).encode()
        if name == record_name:
            record = json.loads(data)
            record["environment"]["ray"] = {"node_id": result.node_id, "attempts": result.attempt,
                                            "retried": result.attempt > 1}
            write_json_atomic(folder / name, record)
            continue
        with atomic_path(folder / name) as tmp:
            tmp.write_bytes(data)
    return result.value
