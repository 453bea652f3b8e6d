"""Mesh extractors (docs/design.md §6): `tsdf` (open3d fusion of rendered depth), `tets`,
`poisson`; shared clean-up in `gsbench.mesh.cleanup`; mesh files of every format read in `gsbench.mesh.files`.

An empty or degenerate mesh is a `MeshError`, never a silent file; its message names the parameters
that produced it.
"""

from gsbench.errors import GsbenchError


class MeshError(GsbenchError):
    """Mesh extraction produced nothing usable (empty, degenerate, non-finite) or got unusable inputs."""
