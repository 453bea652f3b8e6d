"""Plain statistics of a mesh, protocol v1, as docs/evaluation.md §6 states them: ``vertices``, ``faces``,
``components``, ``watertight`` and ``area``, numbers every scene has.

``components`` counts faces joined by shared edges after merging coincident vertices (faces touching at one
vertex only are separate); ``area`` is in the dataset frame, the normalised area × ``Normalisation.scale²``.
``area``, ``vertices`` and ``faces`` describe the mesh and are declared ``higher_is_better=None``: shown, never
ranked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from gsbench.data.camera import Scene
from gsbench.evaluators.base import Diagnostics, Evaluator, MetricInfo
from gsbench.evaluators.geometry import check_frame, load_geometry, read_geometry


@dataclass(frozen=True)
class MeshStatsOptions:
    frame: str = "normalised"


def face_components(mesh) -> int:
    """Connected components of ``mesh``'s faces over shared edges (module docstring)."""
    return len(trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(mesh.faces))))


class MeshStats(Evaluator):
    """Components, watertightness, surface area and size of a mesh."""

    name = "mesh_stats"
    version = 1
    memory_per_face = 380
    requires = ("mesh",)
    needs = ()
    metrics = {
        "components": MetricInfo(False, "", "connected components of faces (shared edges); 1 for one closed object"),
        "watertight": MetricInfo(True, "", "1.0 when every edge has exactly two faces, else 0.0"),
        "area": MetricInfo(None, "units^2", "surface area in the dataset frame (DTU: mm^2); descriptive, not a score"),
        "vertices": MetricInfo(None, "", "vertex count; descriptive, not a score"),
        "faces": MetricInfo(None, "", "face count; descriptive, not a score"),
    }
    Options = MeshStatsOptions

    def validate(self, scene: Scene) -> None:
        """Nothing to check: every scene can be described."""

    def evaluate(self, mesh, scene: Scene, **options) -> dict:
        opts = self.options(**options)
        check_frame(opts.frame)
        diag = Diagnostics()
        with diag.phase("load"):
            geo = read_geometry(mesh)  # not load_geometry: an empty mesh is described (zeros), not an error
            if len(geo.vertices) and geo.is_mesh:
                geo = load_geometry(geo, need_faces=True)
        if not geo.is_mesh:
            diag.warn(f"mesh_stats: {geo.label} has no faces; zeros reported")
            metrics = {"components": 0.0, "watertight": 0.0, "area": 0.0, "vertices": float(len(geo.vertices)),
                       "faces": 0.0}
            return {"metrics": metrics, "protocol": self.protocol(opts), "diagnostics": diag.finish()}
        with diag.phase("topology"):
            merged = trimesh.Trimesh(geo.vertices, geo.faces, process=False)
            merged.merge_vertices()
            components = face_components(merged)
            watertight = bool(merged.is_watertight)
        tri = geo.vertices[geo.faces]
        area = float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())
        scale = float(scene.normalisation.scale) if opts.frame == "normalised" else 1.0
        diag.data.update(area_given_frame=area, scale=scale, merged_vertices=int(len(merged.vertices)))
        return {
            "metrics": {"components": float(components), "watertight": 1.0 if watertight else 0.0,
                        "area": area * scale**2, "vertices": float(len(geo.vertices)), "faces": float(len(geo.faces))},
            "protocol": self.protocol(opts),
            "diagnostics": diag.finish(),
        }
