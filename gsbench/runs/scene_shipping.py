"""A run's scene on a Ray node that shares no disk with the driver (docs/cluster.md §2).

The driver gives each run a `SceneTicket` (`SceneShipper.ticket`); the task places the scene by it (`scene_on_node`)
and sends back the content hash (`folder_hash`) of what it read, which the driver compares with its own
(`check_scene_hash`) before it writes the run's outputs:

- a built-in scene (``synthetic/<name>``) is generated on each node from its name, as on the driver; the hashes
  show the nodes generated the same files;
- a scene folder given by a relative path is shipped: packed once (a tar, at most `SHIP_CAP_BYTES`) and put once
  into Ray's object store, fetched by a node only when its cache (``<GSBENCH_DATA>/shipped/<hash>/``) lacks it,
  unpacked there at the same relative path, and the run reads it from there (the task works in that folder), so
  its configuration, and its run id, are the driver's;
- a scene folder given by an absolute path is read in place on the node, which must hold the same files there;
- with ``executor.scene_paths: shared`` every scene folder is read in place from its path on each node (a relative
  one from the driver's working folder), unchecked: a dataset too large to ship, kept on a shared disk or copied to
  every node (``ray rsync-up``).
"""

from __future__ import annotations

import hashlib
import io
import os
import shutil
import tarfile
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from gsbench.data.cache import cache_dir
from gsbench.data.synthetic.builtin import builtin_name
from gsbench.data.synthetic.make import ensure_scene
from gsbench.errors import ConfigError, DataError, GsbenchError

SCENE_PATHS = ("ship", "shared")  # executor.scene_paths: ship scene folders (and check every scene), or read in place
SHIP_CAP_BYTES = 2 << 30  # the largest scene folder shipped through the object store
SHIPPED = "shipped"  # the node's cache of shipped scenes, under GSBENCH_DATA


@dataclass(frozen=True)
class SceneTicket:
    """How a node gets a run's ``scene``: ``kind`` builtin (generated), shipped (``payload``: a one-element list
    holding the ObjectRef of its tar, so that Ray passes the reference, not the bytes), in_place (an absolute folder
    the node must hold) or shared (read in place unchecked, relative paths from ``cwd``); ``content_hash`` of the
    driver's copy (None when unchecked)."""

    scene: str
    kind: str
    content_hash: str | None = None
    payload: list | None = None
    cwd: str | None = None


def folder_hash(folder: Path) -> str:
    """sha256 over the folder's files: each one's path relative to ``folder`` and its bytes, in path order."""
    digest = hashlib.sha256()
    folder = Path(folder)
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(path.relative_to(folder).as_posix().encode() + b"\0")
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")
    return digest.hexdigest()


def folder_size(folder: Path) -> int:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file())


class SceneShipper:
    """The driver's side: one `SceneTicket` per scene, a shipped folder packed and put into the object store once.
    ``put``: ``ray.put``; ``scene_paths``: one of `SCENE_PATHS`."""

    def __init__(self, put, scene_paths: str = "ship"):
        if scene_paths not in SCENE_PATHS:
            raise ConfigError(f"executor.scene_paths must be one of {', '.join(SCENE_PATHS)}, got {scene_paths!r}")
        self.put, self.scene_paths = put, scene_paths
        self._tickets: dict = {}

    def ticket(self, scene: str) -> SceneTicket:
        if scene not in self._tickets:
            self._tickets[scene] = self._make(scene)
        return self._tickets[scene]

    def _make(self, scene: str) -> SceneTicket:
        if builtin_name(scene) is not None:
            return SceneTicket(scene, "builtin", folder_hash(ensure_scene(scene)))
        if self.scene_paths == "shared":
            return SceneTicket(scene, "shared", cwd=os.getcwd())
        folder = Path(scene)
        if folder.is_absolute():
            return SceneTicket(scene, "in_place", folder_hash(folder))
        if ".." in folder.parts:
            raise ConfigError(f"scene {scene}: a shipped scene is unpacked on each node at its path relative to the "
                              "working folder, and this one leaves it; fix: run gsbench sweep from a folder that holds "
                              "the scene, or set executor.scene_paths: shared (docs/cluster.md §2)")
        size = folder_size(folder)
        if size > SHIP_CAP_BYTES:
            raise ConfigError(f"scene {scene}: {size / 2**30:.1f} GiB, more than the {SHIP_CAP_BYTES / 2**30:g} GiB "
                              "the Ray executor ships to its nodes; fix: put it at one path on every node (a shared "
                              "disk, or `ray rsync-up`) and set executor.scene_paths: shared in the sweep file "
                              "(docs/cluster.md §2)")
        return SceneTicket(scene, "shipped", folder_hash(folder), payload=[self.put(pack(folder, scene))])


def pack(folder: Path, arcname: str) -> bytes:
    """``folder`` as an uncompressed tar whose members lie under ``arcname``."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(folder, arcname=arcname)
    return buffer.getvalue()


def unpack_once(ticket: SceneTicket, get) -> Path:
    """The node's staging folder of a shipped scene, ``<GSBENCH_DATA>/shipped/<hash>``, holding it at its relative
    path; fetched (``get``: ``ray.get``) and unpacked only when missing, into a temporary folder renamed into place,
    so tasks unpacking it at once on one node leave one whole copy."""
    staging = cache_dir() / SHIPPED / ticket.content_hash
    if not (staging / ticket.scene).is_dir():
        staging.parent.mkdir(parents=True, exist_ok=True)
        partial = Path(tempfile.mkdtemp(prefix=f".{ticket.content_hash}.", dir=staging.parent))
        with tarfile.open(fileobj=io.BytesIO(get(ticket.payload[0])), mode="r") as tar:
            tar.extractall(partial, filter="data")
        try:
            os.rename(partial, staging)
        except OSError:  # another task placed it first
            shutil.rmtree(partial)
    return staging


@contextmanager
def scene_on_node(ticket: SceneTicket, get):
    """Place ``ticket``'s scene on this node for the block and yield the content hash of what the run will read
    (None for a shared one); a shipped scene, and a shared one given relatively, make the block work in the folder
    that holds it. ``get``: ``ray.get``, which fetches a shipped scene's tar."""
    if ticket.kind == "builtin":
        yield folder_hash(ensure_scene(ticket.scene))
        return
    if ticket.kind == "in_place":
        if not Path(ticket.scene).is_dir():
            raise DataError(f"scene {ticket.scene}: no such folder on this node; fix: copy it to that path on every "
                            "node, or give the scene relative to the working folder so the driver ships it "
                            "(docs/cluster.md §2)")
        yield folder_hash(Path(ticket.scene))
        return
    if ticket.kind == "shared":
        with working_folder(ticket.cwd if Path(ticket.cwd).is_dir() else None):
            yield None
        return
    staging = unpack_once(ticket, get)
    with working_folder(staging):
        yield folder_hash(staging / ticket.scene)


@contextmanager
def working_folder(folder):
    """Work in ``folder`` for the block (None: stay)."""
    before = os.getcwd()
    if folder is not None:
        os.chdir(folder)
    try:
        yield
    finally:
        os.chdir(before)


def check_scene_hash(scene: str, expected: str | None, found: str | None, node_id: str) -> None:
    """A GsbenchError when the node read ``scene`` with other content than the driver's (both hashes known)."""
    if expected is None or found == expected:
        return
    raise GsbenchError(f"scene {scene}: node {node_id[:12]} read other files than the driver's (content hash "
                       f"{str(found)[:12]}, the driver's {expected[:12]}); a built-in scene must be generated alike "
                       "on every node and a folder must be the same; fix: install the same gsbench and libraries on "
                       "every node (docs/cluster.md §4), or copy the folder there again")
