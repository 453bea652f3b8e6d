"""Built-in synthetic scenes with exact ground truth, written in the official DTU or TnT layouts.

A scene is planned (`plan_scene`: object, cameras, frames, normalisation; deterministic from the seed)
and then written (`write_scene`). Frames, all similarities composed in float64:

    object frame (shapes.py: z up, extent 1)  --obj_to_gt-->  GT frame (DTU: mm world; TnT: metres)
    GT frame  --gt_to_dataset-->  dataset frame (DTU: the same; TnT: the COLMAP frame)
    normalised training frame  --normalisation-->  dataset frame

Rendering happens in the object frame (small coordinates, float32-safe even for ``spot-km``).

DTU layout (``dtu``; ``dtu-colmap`` writes the 2DGS variant: ``images/`` + ``sparse/0`` instead of
``image/``): ``image/000000.png``, ``mask/000.png``, ``cameras.npz`` (world_mat_i in mm, integer
pixel centres; scale_mat_i with ``s = 1.1 x`` the object's bounding-sphere radius, centre = the
object's bounding-box centre), and GT ``Points/stl/stl{scan:03d}_total.ply`` (surface samples 0.2 mm
apart seen by >= 2 views; the object is 100 mm long, which gives about 120-250 thousand points),
``ObsMask/ObsMask{scan}_10.mat`` (``Res`` = 1 mm; surface samples 0.5 mm apart seen by >= 2 views,
dilated by 4 mm) and
``ObsMask/Plane{scan}.mat`` (``P`` = up > lowest GT point - 1 mm, up = the object frame's z: the GT frame's z in
the synthetic rigs, DTU's table normal in DTU's rig). Scan numbers
are 1001 + the scene's index in `BUILTIN_SCENES`.

Why the DTU ``stl`` holds only samples seen by >= 2 views (generator v6): DTU's reference scans come
from a structured-light scanner on the same robot arm as the cameras, so they contain the surface
the cameras observe and nothing else (no underside, no occluded folds). A complete-surface stl made
completeness measure the camera cap instead of the method: on ``synthetic/spot`` 21% of the samples
are unseen, and TSDF of the *exact* GT depth at 200x150 scored completeness 2.18 mm, 7.3 mm on the
unseen samples. TnT's GT is a laser scan independent of the images, so the TnT ``{name}.ply`` stays
the whole surface (the crop box bounds it, as in the official data). ``gt_mesh.ply`` is always whole.

TnT layout (``tnt``): ``images/000000.png``, ``sparse/0`` (PINHOLE, points3D = 10,000 noisy surface
samples with their albedo), ``{name}.ply`` (GT samples tau/2 apart), ``{name}.json`` (crop: the convex
hull of the GT in xy grown by 2% of the object size, z range likewise), ``{name}_trans.txt``
(COLMAP -> GT), ``{name}_COLMAP_SfM.log`` (camera-to-world, COLMAP frame, image-name order).
tau = 0.5% of the object size (GT units), stored in the meta file.

Scenes with an environment (added in generator v7, which left the older scenes' content unchanged
and only fixed the ``.mat`` header text so that equal scenes are equal bytes; ``environment.py``,
objects in ``objects.py``, textures in ``textures.py``): the object stands on a table in a room
(``dtu-*``: Spot, a stool with thin legs, a bowl with a handle, stepped prisms with sharp edges, a
finely patterned vase, a uniform pebble stack) or on the ground among props, buildings or under a
sky dome (``tnt-spot``, ``tnt-yard``, ``tnt-sky``). Object and environment are ray-cast together;
images are full views (no black background), masks are the pixels whose centre ray first hits the
object (DTU masks), and ``gt_depth``/``gt_normal`` are the first hit of anything. Their GT:

- DTU: the stl holds the object samples and the table-top samples within 0.8 object sizes (80 mm)
  of the object's axis (minus the footprint), each kept when seen by >= 2 views (`seen_by_views`:
  the test of `visible_counts` for depth maps without background); ``ObsMask`` is built from the
  same samples; ``Plane`` = z > table top + 1 mm (``DTU_PLANE_ABOVE_TABLE``), so completeness
  ignores the table while accuracy still scores reconstructed table points inside ``ObsMask``
  against the stl table. They are written in the 2DGS ``dtu-colmap`` layout by default.
- TnT: ``{name}.ply`` holds the object and the ground inside the crop volume (``World.gt_polygon`` x
  ``gt_z``, written as the crop json), samples tau/2 apart; props and backdrops lie outside the crop.
- SfM-like init points (`_init_points`): 25,000 noisy first hits of random pixel rays of the views,
  so they cover the object, the table and the room as the images do.
- ``gt_mesh.ply`` is the object only; ``gt_scene_mesh.ply`` is everything ray-cast (object and
  environment, dataset frame, not subdivided).

Both layouts also get ``gt_depth/{stem}.npy`` (camera z, normalised frame) and ``gt_normal/{stem}.npy``
(camera-space unit normals) per view, and the ``gsbench_scene.json`` meta file.

Resolution: ``res`` None (default 0.25 of the full 1600x1200 DTU / 1920x1080 TnT size), a float
factor of the full size, or an explicit ``(W, H)``; fx = fy = focal x W, principal point at the image
centre.
"""

from __future__ import annotations

import dataclasses
import importlib.util
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.io import savemat
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from gsbench.data.camera import Camera, Normalisation
from gsbench.data.colmap import write_colmap_model
from gsbench.data.dtu import normalisation_from_scale_mat, write_cameras_npz
from gsbench.data.frame import FrameQuantities, Region, crop_region, frame_quantities
from gsbench.data.images import write_mask, write_rgb
from gsbench.data.meta import write_meta
from gsbench.data.reference_rigs import barn_rig, dtu_rig
from gsbench.data.similarity import decompose, similarity, transform_camera, transform_points
from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.data.synthetic.environment import World, make_environment
from gsbench.data.synthetic.framing import FRAMINGS, framed_distance, parse_framing
from gsbench.data.synthetic.groundtruth import (
    observation_mask,
    sample_init_points,
    sample_surface,
    sample_view_points,
    sample_world_gt,
    seen_by_views,
    visible_counts,
    write_point_cloud,
)
from gsbench.data.synthetic.mesh_file import file_digest, read_mesh_object
from gsbench.data.synthetic.primitives import Surface
from gsbench.data.synthetic.render import MAX_BOUNCES, MIN_WEIGHT, Renderer
from gsbench.data.synthetic.rigs import REAL_RIGS, barn_cameras, dtu_cameras, make_rig
from gsbench.data.synthetic.shapes import NAMED_ALBEDOS, make_surface, named_albedo
from gsbench.data.tnt import nerfpp_normalisation, write_crop_json, write_log
from gsbench.errors import DataError, RegistryError
from gsbench.training.progress import ProgressLines

GENERATOR_VERSION = 8
DEFAULT_RES = 0.25
SCAN_BASE = 1001
GT_MESH_NAME = "gt_mesh.ply"
DTU_GT_SPACING = 0.2
DTU_OBS_RES = 1.0
DTU_OBS_DILATION = 4.0
DTU_MIN_VIEWS = 2  # a GT sample is 'scanned' (stl) and 'observed' (ObsMask) when seen by this many views
TAU_FRACTION = 0.005
INIT_POINTS = 10_000
INIT_NOISE = 0.004
CROP_MARGIN = 0.02
WORLD_INIT_POINTS = 25_000
WORLD_INIT_NOISE = 0.002  # x the distance from the camera
DTU_PLANE_ABOVE_TABLE = 1.0  # mm
SCENE_MESH_NAME = "gt_scene_mesh.ply"
PYMESHLAB_SAMPLES = "tests/sample_meshes"  # the scanned meshes pymeshlab's wheel ships
DEFAULT_SUPERSAMPLE = 2  # rays per pixel side of the RGB images (area sampling); 1 = the pixel centre only


@dataclass(frozen=True)
class FormatDefaults:
    """Per-layout defaults: full image size, views, fx/W, rig, distance in object radii, object size
    and position in the GT frame, rotation of the object about GT z (degrees), GT units."""

    full_size: tuple[int, int]
    views: int
    focal: float
    rig: str
    distance: float
    size: float
    offset: tuple[float, float, float]
    yaw: float
    units: str


FORMATS = {
    "dtu": FormatDefaults((1600, 1200), 49, 1.1, "cap", 3.5, 100.0, (30.0, -20.0, 600.0), 0.0, "mm"),
    "tnt": FormatDefaults((1920, 1080), 48, 0.6, "ring", 4.0, 1.5, (2.0, -1.0, 0.5), 30.0, "m"),
}


@dataclass(frozen=True)
class SyntheticSpec:
    """What makes a built-in scene special; None fields take the layout's `FormatDefaults`.

    ``fmt`` is the layout it is written in by default (``dtu``, ``dtu-colmap`` or ``tnt``);
    ``environment`` (``environment.py``: room, ground, yard, sky) puts the object in surroundings.
    ``mesh`` (a file, or ``pymeshlab:<path>`` inside the installed pymeshlab package) replaces
    ``shape`` by a mesh file read by ``mesh_file.py`` with ``up``, ``yaw``, ``largest_part`` and ``smooth``;
    its ``albedo`` ``file`` means the file's own colours. ``framing`` (an object share of the image,
    ``framing.py``) places the cameras at the distance that gives that share instead of ``distance``.
    ``glass_ior`` makes the object clear glass of that index of refraction (``render.py``: refraction,
    Fresnel reflection, total internal reflection, bounded bounces); None: opaque.
    ``size``/``offset``/``units`` and the COLMAP frame (GT -> COLMAP: scale ``colmap_scale``,
    rotation ``colmap_euler`` (xyz degrees), object centre at ``colmap_center``) apply only when the
    scene is written in its own layout ``fmt``; in Barn's rig the scale is Barn's instead (`plan_spec`).
    """

    shape: str = "spot"
    albedo: str = "texture"
    fmt: str = "dtu"
    rig: str | None = None
    distance: float | None = None
    specular: float = 0.0
    size: float | None = None
    offset: tuple[float, float, float] | None = None
    units: str | None = None
    colmap_scale: float = 0.4
    colmap_euler: tuple[float, float, float] = (20.0, -35.0, 110.0)
    colmap_center: tuple[float, float, float] = (0.3, -1.2, 2.0)
    environment: str | None = None
    mesh: str | None = None
    up: str = "y"
    yaw: float = 0.0
    largest_part: bool = False
    smooth: int = 0
    framing: float | None = None
    glass_ior: float | None = None


GLASS_IOR = 1.5  # crown glass (n_d 1.52 for BK7, rounded as renderers commonly do)

SPECS = {
    "synthetic/spot": SyntheticSpec(),
    "synthetic/spot-tnt": SyntheticSpec(fmt="tnt"),
    "synthetic/thin-plate": SyntheticSpec(shape="plate", albedo="procedural", rig="band"),
    "synthetic/textureless": SyntheticSpec(albedo="uniform"),
    "synthetic/spot-far": SyntheticSpec(distance=12.0),
    "synthetic/spot-km": SyntheticSpec(fmt="tnt", size=1500.0, offset=(512_300.0, 4_205_700.0, 850.0),
                                       units="m (km-scale object, UTM-like coordinates)", colmap_scale=1e-3,
                                       colmap_center=(1200.0, -800.0, 40.0)),
    "synthetic/dtu-spot": SyntheticSpec(fmt="dtu-colmap", environment="room"),
    "synthetic/dtu-stool": SyntheticSpec(shape="stool", albedo="wood", fmt="dtu-colmap", environment="room"),
    "synthetic/dtu-bowl": SyntheticSpec(shape="bowl", albedo="glaze", fmt="dtu-colmap", environment="room"),
    "synthetic/dtu-blocks": SyntheticSpec(shape="blocks", albedo="painted", fmt="dtu-colmap", environment="room"),
    "synthetic/dtu-fine": SyntheticSpec(shape="vase", albedo="fine", fmt="dtu-colmap", environment="room"),
    "synthetic/dtu-plain": SyntheticSpec(shape="pebbles", albedo="uniform", fmt="dtu-colmap", environment="room"),
    "synthetic/tnt-spot": SyntheticSpec(fmt="tnt", environment="ground"),
    "synthetic/tnt-yard": SyntheticSpec(shape="yard", albedo="facade", fmt="tnt", environment="yard", distance=1.8, size=20.0,
                                        offset=(35.0, -12.0, 3.0), colmap_scale=0.1),
    "synthetic/tnt-sky": SyntheticSpec(fmt="tnt", environment="sky"),
    "synthetic/dtu-bunny": SyntheticSpec(mesh=f"pymeshlab:{PYMESHLAB_SAMPLES}/bunny.obj", albedo="glaze", fmt="dtu-colmap",
                                         environment="room", yaw=-90.0, framing=FRAMINGS["dtu"]),
    "synthetic/dtu-face": SyntheticSpec(mesh=f"pymeshlab:{PYMESHLAB_SAMPLES}/rangemaps/face000.ply", albedo="stone",
                                        fmt="dtu-colmap", environment="room", up="-z", largest_part=True,
                                        framing=FRAMINGS["dtu"]),
    "synthetic/dtu-spot-near": SyntheticSpec(fmt="dtu-colmap", environment="room", framing=FRAMINGS["dtu"]),
    "synthetic/dtu-bunny-far": SyntheticSpec(mesh=f"pymeshlab:{PYMESHLAB_SAMPLES}/bunny.obj", albedo="glaze", fmt="dtu-colmap",
                                             environment="room", yaw=-90.0, framing=FRAMINGS["small"]),
    "synthetic/dtu-bunny-smooth": SyntheticSpec(mesh=f"pymeshlab:{PYMESHLAB_SAMPLES}/bunny.obj", albedo="glaze",
                                                fmt="dtu-colmap", environment="room", yaw=-90.0, smooth=200,
                                                framing=FRAMINGS["dtu"]),
    **{f"synthetic/dtu-{name}{twin}": SyntheticSpec(shape=shape, albedo="glaze", fmt="dtu-colmap", environment="room",
                                                    framing=FRAMINGS["dtu"], glass_ior=ior)
       for name, shape in (("glass-orb", "orb"), ("glass-wine", "wineglass"), ("glass-bottle", "bottle"))
       for twin, ior in (("", GLASS_IOR), ("-opaque", None))},
}
RIGGED = {  # the scenes of the dtu-framed and tnt-like boards, in the datasets' own rigs (generator v8)
    "dtu-rig-bunny": "dtu-bunny", "dtu-rig-face": "dtu-face", "dtu-rig-spot": "dtu-spot-near",
    "tnt-rig-spot": "tnt-spot", "tnt-rig-yard": "tnt-yard", "tnt-rig-sky": "tnt-sky",
}
SPECS.update({f"synthetic/{new}": dataclasses.replace(SPECS[f"synthetic/{old}"], distance=None,
                                                      rig="dtu" if new.startswith("dtu") else "barn")
              for new, old in RIGGED.items()})
MESH_SCAN = 2001  # DTU scan number of scenes made from a user's mesh file (built-ins: SCAN_BASE + index)
MESH_ENVIRONMENT = {"dtu": "room", "tnt": "ground"}
LEGACY_MESH_RIG = {"dtu": "cap", "tnt": "ring"}  # the rig of mesh scenes made before generator v8 (no "rig" in their meta)


@dataclass
class ScenePlan:
    """Everything needed to write a synthetic scene (see the module docstring for the frames)."""

    name: str
    fmt: str
    seed: int
    spec: SyntheticSpec
    surface: Surface
    cameras: list[Camera]
    obj_to_gt: np.ndarray
    gt_to_dataset: np.ndarray
    normalisation: Normalisation
    units: str
    scan: int | None = None
    tau: float | None = None
    world: World | None = None
    supersample: int = DEFAULT_SUPERSAMPLE
    description: str = ""
    distance: float = 0.0
    share: float | None = None
    mesh_info: dict | None = None

    @property
    def rendered(self) -> Surface:
        """What the views see: the object in its environment, or the object alone."""
        return self.surface if self.world is None else self.world.surface

    @property
    def obj_to_dataset(self) -> np.ndarray:
        return self.gt_to_dataset @ self.obj_to_gt

    @property
    def dataset_cameras(self) -> list[Camera]:
        return [transform_camera(c, self.obj_to_dataset) for c in self.cameras]

    @property
    def normalised_cameras(self) -> list[Camera]:
        """The cameras a loader must recover, in the normalised training frame."""
        norm = self.normalisation
        to_norm = similarity(1.0 / norm.scale, None, -norm.center / norm.scale) @ self.obj_to_dataset
        return [transform_camera(c, to_norm) for c in self.cameras]

    @property
    def depth_scale(self) -> float:
        """Object-frame lengths -> normalised-frame lengths."""
        return decompose(self.obj_to_dataset)[0] / self.normalisation.scale

    @property
    def short_name(self) -> str:
        return self.name.split("/", 1)[-1]

    @property
    def builtin(self) -> bool:
        return self.name.startswith("synthetic/")


def _image_size(full: tuple[int, int], res) -> tuple[int, int]:
    if res is None:
        res = DEFAULT_RES
    if isinstance(res, (int, float)):
        if res <= 0:
            raise DataError(f"resolution factor must be positive, got {res}; fix: e.g. --res 400 300")
        return max(8, int(round(full[0] * res))), max(8, int(round(full[1] * res)))
    w, h = (int(v) for v in res)
    if w < 8 or h < 8:
        raise DataError(f"image size {w}x{h} is too small; fix: at least 8x8")
    return w, h


def canonical_name(name: str) -> str:
    """``spot`` or ``synthetic/spot`` -> ``synthetic/spot``; unknown names raise with the known list."""
    full = name if name.startswith("synthetic/") else f"synthetic/{name}"
    if full not in SPECS:
        raise RegistryError(f"unknown built-in scene {name!r}; expected one of {sorted(SPECS)}")
    return full


def mesh_path(mesh: str) -> Path:
    """A spec's ``mesh``: a file path, or ``pymeshlab:<path>`` inside the installed pymeshlab package
    (found without importing it)."""
    if not mesh.startswith("pymeshlab:"):
        return Path(mesh)
    spec = importlib.util.find_spec("pymeshlab")
    if spec is None or not spec.submodule_search_locations:
        raise DataError(f"{mesh}: the scanned mesh ships with pymeshlab, which is not installed; fix: pip install pymeshlab")
    return Path(list(spec.submodule_search_locations)[0]) / mesh.split(":", 1)[1]


def _object(spec: SyntheticSpec, seed: int) -> tuple[Surface, dict | None]:
    """The spec's object surface and, for a mesh file, what was read and repaired (for the meta file)."""
    if spec.mesh is None:
        return make_surface(spec.shape, spec.albedo, seed), None
    obj = read_mesh_object(mesh_path(spec.mesh), up=spec.up, yaw=spec.yaw, largest_part=spec.largest_part, smooth=spec.smooth)
    if spec.albedo == "auto":
        spec = dataclasses.replace(spec, albedo="file" if obj.albedo is not None else "procedural")
    if spec.albedo == "file":
        if obj.albedo is None:
            raise DataError(f"{spec.mesh}: the file has no colours (no texture, vertex or face colours); fix: choose a "
                            f"named albedo (--albedo, one of {', '.join(NAMED_ALBEDOS)})")
        albedo = obj.albedo
    else:
        albedo = named_albedo(spec.albedo, obj.vertices, obj.triangles, seed)
    info = dict(obj.source, albedo=spec.albedo, repairs=obj.repairs, largest_part=spec.largest_part)
    if spec.mesh.startswith("pymeshlab:"):
        info["path"] = spec.mesh  # the package's copy, wherever it is installed
    return Surface(vertices=obj.vertices, triangles=obj.triangles, albedo=albedo), info


def plan_scene(name: str, fmt: str | None = None, res=None, seed: int = 0, framing=None) -> ScenePlan:
    """Plan a built-in scene: object, cameras, frames and normalisation (no rendering). ``framing``
    (``framing.parse_framing``) replaces the spec's camera placement."""
    name = canonical_name(name)
    spec = SPECS[name]
    if framing is not None:
        spec = dataclasses.replace(spec, framing=parse_framing(framing))
    return plan_spec(name, spec, fmt or spec.fmt, res, seed, SCAN_BASE + list(BUILTIN_SCENES).index(name),
                     BUILTIN_SCENES[name].description)


def plan_mesh_scene(mesh, *, fmt: str = "dtu-colmap", res=None, seed: int = 0, framing="dtu", up: str = "y",
                    yaw: float = 0.0, albedo: str = "auto", largest_part: bool = False, smooth: int = 0,
                    scan: int = MESH_SCAN, rig: str | None = None) -> ScenePlan:
    """Plan a scene of any mesh file (``gsbench scene make --mesh FILE``): the object on the table in the
    room (DTU layouts) or on the ground among props (TnT). ``rig`` None: the dataset's own (``dtu``: DTU's
    cameras, the object sized to the object share ``framing``; ``barn``: Barn's floor plan, no framing);
    ``cap``/``ring``/``band``: a synthetic rig at the layout's distance or framed by ``framing``.
    ``albedo`` ``auto``: the file's colours, or ``procedural`` when it has none (resolved when the file is
    read, and recorded as the one used)."""
    path = Path(mesh)
    if fmt not in ("dtu", "dtu-colmap", "tnt"):
        raise DataError(f"unknown scene format {fmt!r}; expected dtu, dtu-colmap or tnt")
    base = fmt.split("-")[0]
    rig = rig or next(name for name, layout in REAL_RIGS.items() if layout == base)
    if rig == "barn":
        framing = None
    spec = SyntheticSpec(mesh=str(path.resolve()), albedo=albedo, fmt=fmt, environment=MESH_ENVIRONMENT[base],
                         up=up, yaw=yaw, largest_part=largest_part, smooth=smooth, framing=parse_framing(framing), rig=rig)
    return plan_spec(f"mesh/{path.stem}", spec, fmt, res, seed, scan, f"{path.name} as a {base.upper()}-like scene")


def _cameras_at(spec: SyntheticSpec, d: FormatDefaults, K: np.ndarray, width: int, height: int, radius: float, seed: int):
    """The rig's cameras at ``distance`` bounding radii (the jitter is drawn from ``seed`` alike at every distance)."""

    def cameras(distance: float) -> list[Camera]:
        poses = make_rig(spec.rig or d.rig, d.views, distance * radius, 0.03 * radius, np.random.default_rng(seed))
        return [Camera(K=K, R=R, t=t, width=width, height=height, name=f"{k:06d}.png") for k, (R, t) in enumerate(poses)]

    return cameras


def plan_spec(name: str, spec: SyntheticSpec, fmt: str, res, seed: int, scan: int, description: str) -> ScenePlan:
    """Plan the scene ``spec`` describes, written in layout ``fmt`` (see `plan_scene`)."""
    if fmt not in ("dtu", "dtu-colmap", "tnt"):
        raise DataError(f"unknown scene format {fmt!r}; expected dtu, dtu-colmap or tnt")
    base = fmt.split("-")[0]
    d = FORMATS[base]
    own = base == spec.fmt.split("-")[0]
    rig = spec.rig or d.rig
    if rig in REAL_RIGS and REAL_RIGS[rig] != base:
        raise DataError(f"{name}: the {rig} rig is {REAL_RIGS[rig].upper()}'s; fix: write the scene in a {REAL_RIGS[rig]} layout")
    size = spec.size if own and spec.size else d.size
    offset = spec.offset if own and spec.offset else d.offset
    width, height = _image_size(d.full_size, res)
    f = d.focal * width
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    surface, mesh_info = _object(spec, seed)
    world = None
    if spec.environment:
        world = make_environment(spec.environment, surface, seed)
    if rig == "dtu":
        reference = dtu_rig()
        cameras_at, object_to_training = dtu_cameras(reference, width, height, surface.radius)
    elif rig == "barn":
        if spec.framing is not None:
            raise DataError(f"{name}: Barn's rig stands at Barn's distances from the crop region; fix: no --framing")
        barn = barn_cameras(barn_rig(), _crop_region(surface, world), d.views, width, height, 0.03 * surface.radius,
                            np.random.default_rng(seed))
        cameras_at = lambda distance: barn  # noqa: E731  the floor plan fixes the distances
    else:
        cameras_at = _cameras_at(spec, d, K, width, height, surface.radius, seed)
    distance, share = spec.distance or d.distance, None
    if spec.framing is not None:
        distance, share = framed_distance(surface, cameras_at, spec.framing)
    obj_to_gt = similarity(size, Rotation.from_euler("z", d.yaw, degrees=True).as_matrix(), offset)
    if rig == "dtu":
        scale_mat = np.linalg.inv(reference.to_training)
        obj_to_gt = scale_mat @ object_to_training(distance)
        if surface.radius * decompose(obj_to_gt)[0] > reference.region.radius:
            raise DataError(f"{name}: at this framing the object leaves IDR's unit sphere of DTU's rig (radius "
                            f"{surface.radius * decompose(obj_to_gt)[0]:.0f} mm > {reference.region.radius:.0f} mm); "
                            "fix: a smaller --framing")
    plan = ScenePlan(name=name, fmt=fmt, seed=seed, spec=spec, surface=surface, cameras=cameras_at(distance),
                     obj_to_gt=obj_to_gt, gt_to_dataset=np.eye(4), normalisation=Normalisation(),
                     units=(spec.units if own else None) or d.units, world=world, description=description,
                     distance=distance, share=share, mesh_info=mesh_info)
    r = surface.radius
    if base == "dtu":
        if rig == "dtu":
            plan.normalisation = normalisation_from_scale_mat(scale_mat)
        else:
            plan.normalisation = Normalisation(scale=1.1 * r * size, center=np.asarray(offset, dtype=np.float64), radius=1.0)
        plan.scan = scan
    else:
        cs = spec.colmap_scale if own else SyntheticSpec.colmap_scale
        if rig == "barn":  # Barn's COLMAP frame: the crop radius is Barn's in COLMAP units, so the cameras' extent too
            barn_region = barn_rig().region
            cs = barn_region.radius / barn_region.training_scale / (_crop_region(surface, world).radius * size)
        rot = Rotation.from_euler("xyz", spec.colmap_euler, degrees=True).as_matrix()
        center = np.asarray(spec.colmap_center if own else SyntheticSpec.colmap_center)
        plan.gt_to_dataset = similarity(cs, rot, center - cs * rot @ np.asarray(offset))
        plan.normalisation = nerfpp_normalisation(np.array([c.center for c in plan.dataset_cameras]))
        plan.tau = TAU_FRACTION * size
    if rig == "barn":
        plan.distance = frame_quantities(plan.cameras, _crop_region(surface, world)).camera_distance
    return plan


def _crop_region(surface: Surface, world: World | None) -> Region:
    """The object region (`gsbench.data.frame`) of a TnT-like scene in the object frame: its world's GT
    polygon and z range, or the object's own xy hull and z range."""
    if world is not None:
        return crop_region(world.gt_polygon, world.gt_z, 1.0)
    xy = surface.vertices[:, :2]
    return crop_region(xy[ConvexHull(xy).vertices], (surface.vertices[:, 2].min(), surface.vertices[:, 2].max()), 1.0)


def plan_frame(plan: ScenePlan) -> FrameQuantities:
    """The frame quantities (`gsbench.data.frame`) of a planned scene, in its GT frame; a TnT layout's training
    frame is its COLMAP frame (``data.tnt_frame: colmap``)."""
    gt_cameras = [transform_camera(c, plan.obj_to_gt) for c in plan.cameras]
    scale = decompose(plan.obj_to_gt)[0]
    if plan.fmt.startswith("dtu"):
        norm = plan.normalisation
        return frame_quantities(gt_cameras, Region(norm.center, norm.scale, False, norm.scale))
    local = _crop_region(plan.surface, plan.world)
    centre = transform_points(plan.obj_to_gt, local.centre[None])[0]
    colmap_unit = 1.0 / decompose(plan.gt_to_dataset)[0]  # GT units per COLMAP unit: the training frame's
    return frame_quantities(gt_cameras, Region(centre, local.radius * scale, True, colmap_unit))


def plan_meta(plan: ScenePlan) -> dict:
    """The ``gsbench_scene.json`` content of a plan (compared to skip re-generation). Scenes placed by
    framing record it (``framing``: the share asked for, the distance found and the share measured);
    scenes of a mesh file record the file (``mesh``: path, SHA-256, sizes, colours, repairs)."""
    cam = plan.cameras[0]
    meta = {"name": plan.short_name, "format": plan.fmt, "seed": plan.seed,
            "resolution": [cam.width, cam.height], "units": plan.units, "generator_version": GENERATOR_VERSION,
            "description": plan.description}
    if plan.builtin:
        meta["builtin"] = plan.name
    if plan.scan is not None:
        meta["scan"] = plan.scan
    if plan.tau is not None:
        meta["tau"] = plan.tau
    if plan.supersample != DEFAULT_SUPERSAMPLE:
        meta["supersample"] = plan.supersample
    if plan.spec.rig in REAL_RIGS or plan.mesh_info is not None:
        meta["rig"] = plan.spec.rig or FORMATS[plan.fmt.split("-")[0]].rig
    meta["frame"] = plan_frame(plan).as_dict()
    if plan.spec.framing is not None:
        meta["framing"] = {"object_share": plan.spec.framing, "distance_radii": round(plan.distance, 6),
                           "measured_share": round(plan.share, 4)}
    if plan.mesh_info is not None:
        meta["mesh"] = plan.mesh_info
    if plan.spec.glass_ior is not None:
        meta["glass"] = {"ior": plan.spec.glass_ior, "max_bounces": MAX_BOUNCES, "min_weight": MIN_WEIGHT}
    return meta


def plan_from_meta(meta: dict, root: Path) -> ScenePlan:
    """The plan a generated scene folder was written from (its ``gsbench_scene.json``), to re-render its
    exact surfaces; a mesh scene whose file changed since is refused."""
    common = {"res": tuple(meta["resolution"]), "seed": meta["seed"]}
    framing = meta.get("framing", {}).get("object_share")
    if "builtin" in meta:
        return plan_scene(meta["builtin"], fmt=meta["format"], framing=framing, **common)
    mesh = meta.get("mesh")
    if mesh is None:
        raise DataError(f"{root}: not a generated scene (no 'builtin' or 'mesh' in gsbench_scene.json); fix: the exact "
                        "surface exists only for scenes gsbench made, give a synthetic/<name> or `scene make --mesh` folder")
    path = mesh_path(mesh["path"])
    if not path.is_file() or file_digest(path) != mesh["sha256"]:
        raise DataError(f"{root}: its mesh {path} is gone or changed since the scene was made; fix: restore the file or "
                        "re-make the scene")
    return plan_mesh_scene(path, fmt=meta["format"], framing=framing, up=mesh["up"], yaw=mesh["yaw"], albedo=mesh["albedo"],
                           largest_part=mesh["largest_part"], smooth=mesh.get("taubin_iterations", 0),
                           scan=meta.get("scan", MESH_SCAN), rig=meta.get("rig", LEGACY_MESH_RIG[meta["format"].split("-")[0]]),
                           **common)


def write_scene(plan: ScenePlan, out: Path) -> None:
    """Render every view and write images, masks, GT maps, cameras and GT files into ``out``."""
    out = Path(out)
    image_dir = out / ("image" if plan.fmt == "dtu" else "images")
    dirs = [image_dir, out / "gt_depth", out / "gt_normal"] + ([out / "mask"] if plan.fmt != "tnt" else [])
    for folder in dirs:
        folder.mkdir(parents=True, exist_ok=True)
    renderer = Renderer(plan.rendered, specular=plan.spec.specular, supersample=plan.supersample,
                        glass_ior=plan.spec.glass_ior)
    depths = []
    desc = f"rendering {plan.name}"
    lines = ProgressLines(desc, len(plan.cameras), unit="view")  # a log file's progress, where tqdm is silent
    for k, cam in enumerate(tqdm(plan.cameras, desc=desc, unit="view", disable=None)):
        view = renderer.render(cam)
        stem = Path(cam.name).stem
        write_rgb(image_dir / cam.name, view.rgb)
        if plan.fmt != "tnt":
            write_mask(out / "mask" / f"{k:03d}.png", view.mask)
        np.save(out / "gt_depth" / f"{stem}.npy", (view.depth * plan.depth_scale).astype(np.float32))
        np.save(out / "gt_normal" / f"{stem}.npy", view.normal)
        depths.append(view.depth)
        lines.update(k + 1)
    lines.close()
    if plan.fmt == "tnt":
        _write_tnt(plan, out)
    else:
        _write_dtu(plan, out, depths)
    max_edge = None if plan.tau is None else plan.tau / decompose(plan.obj_to_gt)[0]
    write_gt_mesh(out / GT_MESH_NAME, plan.surface, plan.obj_to_dataset, max_edge)
    if plan.world is not None:
        write_gt_mesh(out / SCENE_MESH_NAME, plan.world.surface, plan.obj_to_dataset, None)
    write_meta(out, plan_meta(plan))


def write_gt_mesh(path: Path, surface: Surface, to_dataset: np.ndarray, max_edge: float | None) -> None:
    """The exact surface in the dataset frame (DTU: mm world; TnT: the COLMAP frame of the cameras).

    Real datasets have no such file; synthetic scenes ship it so a test or a user can evaluate the
    true surface as a perfect reconstruction (`gsbench eval --mesh gt_mesh.ply --frame dataset`) and
    see the protocol's floor. The TnT protocol scores mesh vertices and face centroids, not the surface,
    so for TnT scenes the mesh is subdivided until every edge is at most τ (``max_edge``, object units;
    every surface point is then within about 0.6τ of a vertex or centroid); otherwise even the exact
    surface loses recall where its triangles are larger than τ (measured: recall 0.32 on spot-tnt).
    """
    vertices, triangles = surface.vertices, surface.triangles
    if max_edge is not None:
        vertices, triangles = trimesh.remesh.subdivide_to_size(vertices, triangles, max_edge=max_edge)
    trimesh.Trimesh(transform_points(to_dataset, vertices), triangles, process=False).export(path)


def _init_points(plan: ScenePlan, to_frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SfM-like init points mapped into ``to_frame``: noisy object surface samples with albedo colours,
    or, for a scene with an environment, noisy first hits of random pixel rays of the views."""
    if plan.world is None:
        points, colors = sample_init_points(plan.surface, INIT_POINTS, INIT_NOISE, plan.seed)
    else:
        points, colors = sample_view_points(plan.world.surface, plan.cameras, WORLD_INIT_POINTS, WORLD_INIT_NOISE, plan.seed)
    return transform_points(to_frame, points), colors


def save_mat(path: Path, arrays: dict, **kwargs) -> None:
    """``scipy.io.savemat`` with a fixed header text (scipy writes the creation time into it), so the
    same scene gives the same bytes."""
    savemat(path, arrays, **kwargs)
    with open(path, "r+b") as f:
        f.write(b"MATLAB 5.0 MAT-file, written by gsbench".ljust(116, b" "))


def _write_dtu(plan: ScenePlan, out: Path, depths: list[np.ndarray]) -> None:
    size = decompose(plan.obj_to_gt)[0]

    def samples(spacing):
        if plan.world is None:
            return sample_surface(plan.surface, spacing / size, plan.seed)
        return sample_world_gt(plan.world, spacing / size, plan.seed)[0]

    points_obj = samples(DTU_GT_SPACING)
    points_mm = transform_points(plan.obj_to_gt, points_obj)
    if plan.world is None:
        scanned = visible_counts(points_obj, plan.cameras, depths, tol=TAU_FRACTION) >= DTU_MIN_VIEWS
    else:  # full depth maps (no background): see groundtruth.visible_counts
        scanned = seen_by_views(points_obj, plan.cameras, depths, TAU_FRACTION, DTU_MIN_VIEWS)
    write_point_cloud(out / "Points" / "stl" / f"stl{plan.scan:03d}_total.ply", points_mm[scanned])
    if plan.world is None:
        coarse = samples(DTU_OBS_RES / 2)  # ObsMask needs only ~voxel density
        seen = visible_counts(coarse, plan.cameras, depths, tol=TAU_FRACTION) >= DTU_MIN_VIEWS
    else:  # generator v6 made ObsMask from its own coarser samples; the new scenes reuse the stl samples
        coarse, seen = points_obj, scanned
    obs, bb = observation_mask(transform_points(plan.obj_to_gt, coarse), seen, DTU_OBS_RES, DTU_OBS_DILATION)
    (out / "ObsMask").mkdir()
    save_mat(out / "ObsMask" / f"ObsMask{plan.scan}_10.mat", {"ObsMask": obs, "BB": bb, "Res": np.array([[DTU_OBS_RES]])},
             do_compression=True)
    up = plan.obj_to_gt[:3, 2] / size  # the object frame's z in the GT frame (DTU's rig: not the GT frame's z)
    if plan.world is None:
        height = (points_mm @ up).min() - 1.0
    else:
        height = transform_points(plan.obj_to_gt, np.array([[0.0, 0.0, plan.world.ground_z]]))[0] @ up + DTU_PLANE_ABOVE_TABLE
    plane = np.array([[up[0]], [up[1]], [up[2]], [-height]])
    save_mat(out / "ObsMask" / f"Plane{plan.scan}.mat", {"P": plane})
    norm = plan.normalisation
    scale_mat = similarity(norm.scale, None, norm.center)
    write_cameras_npz(out / "cameras.npz", plan.dataset_cameras, scale_mat)
    if plan.fmt == "dtu-colmap":
        to_norm = np.linalg.inv(scale_mat) @ plan.obj_to_dataset
        points, colors = _init_points(plan, to_norm)
        write_colmap_model(out / "sparse" / "0", plan.normalised_cameras, points, colors)


def _write_tnt(plan: ScenePlan, out: Path) -> None:
    name = plan.short_name
    size = decompose(plan.obj_to_gt)[0]
    if plan.world is None:
        points_gt = transform_points(plan.obj_to_gt, sample_surface(plan.surface, plan.tau / 2 / size, plan.seed))
        xy = points_gt[:, :2]
        hull = xy[ConvexHull(xy).vertices]
        centre = hull.mean(axis=0)
        grown = centre + (hull - centre) * (1.0 + CROP_MARGIN * size / np.linalg.norm(hull - centre, axis=1, keepdims=True))
        margin = CROP_MARGIN * size
        z_range = (points_gt[:, 2].min() - margin, points_gt[:, 2].max() + margin)
    else:
        world = plan.world
        points_gt = transform_points(plan.obj_to_gt, sample_world_gt(world, plan.tau / 2 / size, plan.seed)[0])
        polygon = np.column_stack([world.gt_polygon, np.full(len(world.gt_polygon), world.ground_z)])
        grown = transform_points(plan.obj_to_gt, polygon)[:, :2]  # the GT frame's z is the object's (yaw only)
        z_range = tuple(transform_points(plan.obj_to_gt, np.array([[0.0, 0.0, z] for z in world.gt_z]))[:, 2])
    write_point_cloud(out / f"{name}.ply", points_gt)
    write_crop_json(out / f"{name}.json", grown, *z_range)
    np.savetxt(out / f"{name}_trans.txt", np.linalg.inv(plan.gt_to_dataset))
    cameras = plan.dataset_cameras
    write_log(out / f"{name}_COLMAP_SfM.log", [c.camera_to_world for c in cameras])
    points, colors = _init_points(plan, plan.obj_to_dataset)
    write_colmap_model(out / "sparse" / "0", cameras, points, colors)
