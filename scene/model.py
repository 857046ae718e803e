"""The in-memory scene model: base meshes, instances, materials, lights, camera.

These are plain frozen dataclasses of numpy arrays; the JSON schema that users
write lives in `nprt.scene.schema` and is converted into these by `nprt.scene.json_load`.
"""

from __future__ import annotations

import hashlib
from dataclasses import InitVar, dataclass, field
from functools import cached_property

import numpy as np

from nprt.scene.errors import SceneError

# Precision policy: vertices are stored as float32 (what Embree consumes);
# transforms are float64 so instances far from the origin stay exact.
VERTEX_DTYPE = np.float32
INDEX_DTYPE = np.uint32
TRANSFORM_DTYPE = np.float64

# Largest radiance, irradiance or emission accepted (a point light's intensity counts
# over the scene's size squared): float32's 3.4e38 less 3.4e8 of headroom for what a path
# multiplies it by (a light sample's 1/pdf, Russian roulette's 1/(1 - q), sums over
# samples) before pixels, shadow contributions and throughputs are stored as float32.
MAX_RADIOMETRY = 1e30
# Quad lights whose edges are closer to parallel than this (sine of the angle) have no area.
MIN_QUAD_SINE = 1e-12


@dataclass(frozen=True, eq=False)
class Mesh:
    """One base mesh in its own local space.

    vertices : (v, 3) float32
    faces    : (f, 3) uint32, indices into vertices
    normals  : (v, 3) float32 or None, per-vertex shading normals
    uvs      : (v, 2) float32 or None
    material : index into Scene.materials
    dropped_degenerate : number of zero-area triangles removed at load time
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    uvs: np.ndarray | None = None
    material: int = 0
    dropped_degenerate: int = 0

    @cached_property
    def content_hash(self) -> str:
        """sha256 of the geometry (vertices, faces), independent of name and material."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.vertices, dtype=VERTEX_DTYPE).tobytes())
        h.update(np.ascontiguousarray(self.faces, dtype=INDEX_DTYPE).tobytes())
        return h.hexdigest()

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    @property
    def nbytes(self) -> int:
        """Bytes of geometry a shard holds for this mesh (vertices, faces, normals, uvs)."""
        extra = sum(a.nbytes for a in (self.normals, self.uvs) if a is not None)
        return int(self.vertices.nbytes + self.faces.nbytes + extra)

    @cached_property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 local-space AABB [min, max]."""
        v = self.vertices.astype(np.float64)
        return np.stack([v.min(axis=0), v.max(axis=0)])


@dataclass(frozen=True, eq=False)
class Instance:
    """A placement of a base mesh. transform : (4, 4) float64 affine, local -> world."""

    mesh: int
    transform: np.ndarray


MESH_INDEX_DTYPE = np.int32


@dataclass(frozen=True, eq=False)
class Instances:
    """Every placement of a scene as two read-only arrays, so setup costs O(1) Python
    objects per scene, not per instance. A sequence of `Instance` views for code that
    wants them one at a time (slow for many instances: use the arrays there).

    mesh      : (m,) int32 base mesh of each instance
    transform : (m, 4, 4) float64 affine local -> world
    """

    mesh: np.ndarray
    transform: np.ndarray

    def __post_init__(self):
        mesh = np.asarray(self.mesh)
        xf = np.asarray(self.transform)
        if mesh.ndim != 1 or (mesh.size and not np.issubdtype(mesh.dtype, np.integer)):
            raise SceneError(f"instances: mesh must be a (m,) integer array, "
                             f"got shape {mesh.shape} dtype {mesh.dtype}")
        if xf.shape != (len(mesh), 4, 4) or (xf.size and not np.issubdtype(xf.dtype, np.number)):
            raise SceneError(f"instances: transform must have shape ({len(mesh)}, 4, 4) "
                             f"(one 4x4 matrix per mesh index), got {xf.shape}")
        if mesh.size and (mesh.min() < np.iinfo(MESH_INDEX_DTYPE).min
                          or mesh.max() > np.iinfo(MESH_INDEX_DTYPE).max):
            raise SceneError(f"instances: mesh index {int(np.abs(mesh).max())} out of range")
        mesh = np.array(mesh, MESH_INDEX_DTYPE)  # owned copies, then frozen
        xf = np.array(xf, TRANSFORM_DTYPE)
        mesh.setflags(write=False)
        xf.setflags(write=False)
        object.__setattr__(self, "mesh", mesh)
        object.__setattr__(self, "transform", xf)

    @classmethod
    def of(cls, items) -> Instances:
        """`Instances` as given, or built from a sequence of `Instance`; a transform that
        is not 4x4 is named by its position."""
        if isinstance(items, Instances):
            return items
        items = tuple(items)
        xfs = [np.asarray(i.transform) for i in items]
        for j, x in enumerate(xfs):
            if x.shape != (4, 4):
                raise SceneError(f"instance {j}: transform must be 4x4, got shape {x.shape}")
        mesh = np.array([int(i.mesh) for i in items], np.int64)
        return cls(mesh, np.stack(xfs) if xfs else np.zeros((0, 4, 4)))

    def __len__(self) -> int:
        return len(self.mesh)

    def __getitem__(self, i) -> Instance:
        if not isinstance(i, int | np.integer):
            raise TypeError(f"Instances index must be an integer, got {type(i).__name__}")
        return Instance(int(self.mesh[i]), self.transform[i])

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]


@dataclass(frozen=True, eq=False)
class Material:
    """Diffuse material. albedo : (3,) float; texture : (h, w, 3) float32 linear or None."""

    name: str = "default"
    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    emission: tuple[float, float, float] = (0.0, 0.0, 0.0)
    texture: np.ndarray | None = None

    @property
    def is_emissive(self) -> bool:
        return max(self.emission) > 0.0


@dataclass(frozen=True)
class QuadLight:
    """One-sided emitting parallelogram corner + a*edge_u + b*edge_v, emitting along
    cross(edge_u, edge_v). radiance : (3,) W/(sr m^2)."""

    corner: tuple[float, float, float]
    edge_u: tuple[float, float, float]
    edge_v: tuple[float, float, float]
    radiance: tuple[float, float, float]


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light. intensity : (3,) W/sr."""

    position: tuple[float, float, float]
    intensity: tuple[float, float, float]


@dataclass(frozen=True)
class DirectionalLight:
    """Light arriving from infinitely far along `direction` (the direction light travels).
    irradiance : (3,) W/m^2 on a surface facing the light."""

    direction: tuple[float, float, float]
    irradiance: tuple[float, float, float]


@dataclass(frozen=True)
class Environment:
    """Radiance for escaped rays. kind 'constant' uses `radiance`; 'sky' blends
    `horizon` to `zenith` by the direction's +y component."""

    kind: str = "constant"
    radiance: tuple[float, float, float] = (0.0, 0.0, 0.0)
    zenith: tuple[float, float, float] = (0.0, 0.0, 0.0)
    horizon: tuple[float, float, float] = (0.0, 0.0, 0.0)


# Default near distance of a camera, relative to its eye-to-target distance: far above
# the float32 rounding of a surface the eye may sit on (1e-7 relative), far below any
# geometry a view is framed to show.
NEAR_REL = 1e-5


@dataclass(frozen=True)
class Camera:
    """Pinhole look-at camera; fov_deg is the vertical field of view. near: the distance
    of the near plane along the view axis (surfaces before it are not seen, as glTF's
    znear); None: NEAR_REL times |target - eye|, so it scales with the scene."""

    eye: tuple[float, float, float] = (0.0, 0.0, 5.0)
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov_deg: float = 45.0
    near: float | None = None

    @property
    def near_distance(self) -> float:
        """The near plane's distance from the eye along the view axis, in scene units."""
        if self.near is not None:
            return float(self.near)
        view = np.asarray(self.target, np.float64) - np.asarray(self.eye, np.float64)
        return NEAR_REL * float(np.linalg.norm(view))


class SceneViews:
    """What a scene offers besides its fields, for a `Scene` and for a `nprt.scene.meta.SceneMeta`
    alike: both have `meshes` (each with name, n_faces, nbytes, bounds, content_hash),
    `instances` and `animation`, so partitioning, planning and frames run on either."""

    @property
    def frames(self) -> int:
        """Number of frames: 1 for a scene without animation."""
        return 1 if self.animation is None else self.animation.frames

    def at_frame(self, frame: int):
        """This scene on `frame`, sharing its meshes (`nprt.scene.animation.scene_at`)."""
        from nprt.scene.animation import scene_at

        return scene_at(self, frame)

    def _check_animation(self) -> None:
        anim = self.animation
        if anim is not None and len(anim.instances) and \
                int(anim.instances.max()) >= len(self.instances):
            raise SceneError(f"animation: instance {int(anim.instances.max())} does not "
                             f"exist (the scene has {len(self.instances)})")

    @property
    def instance_mesh(self) -> np.ndarray:
        """(m,) int32 base mesh of each instance (read-only)."""
        return self.instances.mesh

    @property
    def instance_transform(self) -> np.ndarray:
        """(m, 4, 4) float64 local -> world transform of each instance (read-only)."""
        return self.instances.transform

    def instances_of_mesh(self, mesh: int) -> np.ndarray:
        """(k,) int64 the instances of base mesh `mesh`, ascending."""
        return np.flatnonzero(self.instance_mesh == mesh)

    @property
    def instanced_triangles(self) -> int:
        faces = np.array([m.n_faces for m in self.meshes], np.int64)
        return int(faces[self.instance_mesh].sum())

    @property
    def mesh_bytes(self) -> int:
        return int(sum(m.nbytes for m in self.meshes))

    def summary(self) -> dict:
        return {
            "name": self.name,
            "base_meshes": len(self.meshes),
            "instances": len(self.instances),
            "instanced_triangles": self.instanced_triangles,
            "base_mesh_triangles": int(sum(m.n_faces for m in self.meshes)),
            "mesh_bytes": self.mesh_bytes,
            "lights": len(self.quad_lights) + len(self.point_lights)
            + len(self.directional_lights),
            "frames": self.frames,
        }


@dataclass(frozen=True, eq=False)
class Scene(SceneViews):
    """`instances` may be given as a sequence of `Instance`; it is kept as `Instances`.
    animation: a `nprt.scene.animation.Animation` (frames of instance transforms and lights),
    or None; the scene's own instances and lights are those of frame 0. check_meshes=False
    skips re-validating meshes known valid (`nprt.scene.animation.scene_at` makes frames)."""

    meshes: tuple[Mesh, ...]
    instances: Instances
    materials: tuple[Material, ...] = (Material(),)
    quad_lights: tuple[QuadLight, ...] = ()
    point_lights: tuple[PointLight, ...] = ()
    directional_lights: tuple[DirectionalLight, ...] = ()
    environment: Environment = field(default_factory=Environment)
    camera: Camera = field(default_factory=Camera)
    name: str = "scene"
    animation: object | None = None
    check_meshes: InitVar[bool] = True

    def __post_init__(self, check_meshes: bool):
        object.__setattr__(self, "instances", Instances.of(self.instances))
        validate_scene(self, check_meshes)
        self._check_animation()


def validate_mesh(mesh: Mesh, where: str) -> None:
    """Refuse meshes the renderer cannot trace; `where` names the mesh for the error."""
    v, f = mesh.vertices, mesh.faces
    if v.ndim != 2 or v.shape[1] != 3:
        raise SceneError(f"{where}: vertices must have shape (v, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise SceneError(f"{where}: faces must have shape (f, 3), got {f.shape}")
    if len(v) == 0 or len(f) == 0:
        raise SceneError(f"{where}: mesh is empty ({len(v)} vertices, {len(f)} faces)")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise SceneError(
            f"{where}: vertex {i} is not finite ({v[i].tolist()}); "
            f"{int(bad.sum())} non-finite vertices in all"
        )
    if f.max() >= len(v):
        raise SceneError(f"{where}: face index {int(f.max())} out of range for {len(v)} vertices")
    for name, arr, width in (("normals", mesh.normals, 3), ("uvs", mesh.uvs, 2)):
        if arr is not None and arr.shape != (len(v), width):
            raise SceneError(
                f"{where}: {name} must have shape ({len(v)}, {width}), got {arr.shape}"
            )


def validate_transform(t: np.ndarray, where: str) -> None:
    if t.shape != (4, 4):
        raise SceneError(f"{where}: transform must be 4x4, got shape {t.shape}")
    validate_transforms(t[None], lambda _: where)


def validate_transforms(t: np.ndarray, where) -> None:
    """Refuse non-finite, non-affine or singular transforms t (m, 4, 4), vectorised; the
    error names the first bad one through where(i) -> str."""
    t = np.asarray(t, TRANSFORM_DTYPE)
    if len(t) == 0:
        return
    finite = np.isfinite(t).all(axis=(1, 2))
    affine = np.isclose(t[:, 3], [0.0, 0.0, 0.0, 1.0]).all(axis=1)
    lin = np.where(finite[:, None, None], t[:, :3, :3], 1.0)  # det of NaN warns
    det = np.linalg.det(lin)
    scale = np.abs(lin).max(axis=(1, 2))
    # Relative test: a 1e-4 uniform scale (det 1e-12) is legitimate, a rank-deficient one is not.
    singular = (scale == 0.0) | (np.abs(det) <= 1e-9 * scale**3)
    bad = ~finite | ~affine | singular
    if not bad.any():
        return
    i = int(np.flatnonzero(bad)[0])
    if not finite[i]:
        raise SceneError(f"{where(i)}: transform has non-finite entries")
    if not affine[i]:
        raise SceneError(f"{where(i)}: transform is not affine (last row {t[i, 3].tolist()})")
    raise SceneError(f"{where(i)}: transform is singular (det={det[i]:.3g})")


def validate_scene(scene: SceneViews, check_meshes: bool = True) -> None:
    """check_meshes=False for metadata (`SceneMeta`), whose meshes were checked when it
    was computed and whose vertex arrays are not here, and for a frame of a validated
    scene, whose meshes it shares."""
    if not scene.meshes:
        raise SceneError(f"scene {scene.name!r}: no meshes")
    if not len(scene.instances):
        raise SceneError(f"scene {scene.name!r}: no instances")
    for i, m in enumerate(scene.meshes):
        if check_meshes:
            validate_mesh(m, f"mesh {i} ({m.name!r})")
        if not 0 <= m.material < len(scene.materials):
            raise SceneError(f"mesh {i} ({m.name!r}): material {m.material} does not exist")
    mesh = scene.instance_mesh
    bad = np.flatnonzero((mesh < 0) | (mesh >= len(scene.meshes)))
    if len(bad):
        raise SceneError(f"instance {int(bad[0])}: mesh {int(mesh[bad[0]])} does not exist")
    validate_transforms(scene.instance_transform,
                        lambda i: f"instance {i} (mesh {scene.meshes[mesh[i]].name!r})")
    validate_radiometry(scene)
    validate_camera(scene.camera)


def _vector(value, field: str) -> np.ndarray:
    """(3,) float64 of a finite 3-vector, or a SceneError naming the field."""
    v = np.asarray(value, np.float64)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise SceneError(f"{field}: must be 3 finite numbers, got {value!r}")
    return v


def _radiometry(value, field: str, scale: float = 1.0) -> None:
    """value: an RGB radiance, irradiance or emission (scale 1), or an intensity over
    `scale` = the scene's size squared."""
    v = _vector(value, field)
    if (v < 0).any():
        raise SceneError(f"{field}: must not be negative, got {v.tolist()}")
    if v.max() / scale > MAX_RADIOMETRY:
        per = "" if scale == 1.0 else f" over the scene's size squared ({scale:.3g})"
        raise SceneError(f"{field}: {v.tolist()}{per} exceeds {MAX_RADIOMETRY:g}: the image "
                         f"would overflow float32")


def validate_radiometry(scene: Scene) -> None:
    """Refuse radiometry whose image would overflow float32, quad lights without area
    and directional lights without a direction; errors name the field."""
    for i, m in enumerate(scene.materials):
        _radiometry(m.emission, f"materials[{i}] ({m.name!r}).emission")
    env = scene.environment
    for name in ("radiance", "zenith", "horizon"):
        _radiometry(getattr(env, name), f"environment.{name}")
    for i, q in enumerate(scene.quad_lights):
        where = f"quad_lights[{i}]"
        _vector(q.corner, f"{where}.corner")
        u, v = _vector(q.edge_u, f"{where}.edge_u"), _vector(q.edge_v, f"{where}.edge_v")
        area = float(np.linalg.norm(np.cross(u, v)))
        if not area > MIN_QUAD_SINE * float(np.linalg.norm(u) * np.linalg.norm(v)):
            raise SceneError(f"{where}: zero area (edge_u {u.tolist()} and edge_v "
                             f"{v.tolist()} are zero or parallel)")
        _radiometry(q.radiance, f"{where}.radiance")
    if scene.point_lights:
        wb = instance_world_bounds(scene)
        size = float(np.linalg.norm(wb[:, 1].max(axis=0) - wb[:, 0].min(axis=0)))
        for i, p in enumerate(scene.point_lights):
            _vector(p.position, f"point_lights[{i}].position")
            _radiometry(p.intensity, f"point_lights[{i}].intensity", max(size * size, 1e-300))
    for i, d in enumerate(scene.directional_lights):
        where = f"directional_lights[{i}]"
        length = float(np.linalg.norm(_vector(d.direction, f"{where}.direction")))
        if not length > 0.0:
            raise SceneError(f"{where}.direction: zero length ({list(d.direction)})")
        _radiometry(d.irradiance, f"{where}.irradiance")


def validate_camera(cam: Camera) -> None:
    eye, target = _vector(cam.eye, "camera.eye"), _vector(cam.target, "camera.target")
    up = _vector(cam.up, "camera.up")
    view = target - eye
    if not np.linalg.norm(view) > 0.0:
        raise SceneError(f"camera: eye and target coincide ({eye.tolist()})")
    if not np.linalg.norm(np.cross(view, up)) > 0.0:
        raise SceneError(f"camera.up: {up.tolist()} is zero or parallel to the view direction")
    if not 0.0 < cam.fov_deg < 180.0:
        raise SceneError(f"camera.fov_deg: must lie in (0, 180), got {cam.fov_deg!r}")
    if cam.near is not None and not (np.isfinite(cam.near) and cam.near >= 0.0):
        raise SceneError(f"camera.near: must be a finite distance >= 0, got {cam.near!r}")


def instance_world_bounds(scene: Scene) -> np.ndarray:
    """World AABBs of all instances (the top-level boxes).

    returns : (n_instances, 2, 3) float64, [min, max] per instance
    """
    mesh_bounds = np.stack([m.bounds for m in scene.meshes])  # (meshes, 2, 3)
    local = mesh_bounds[scene.instance_mesh]  # (n, 2, 3)
    xf = scene.instance_transform  # (n, 4, 4)
    centre, half = local.mean(axis=1), 0.5 * (local[:, 1] - local[:, 0])
    # Arvo: the box of a transformed box is centre R c + t, half-extent |R| e.
    wc = np.einsum("nij,nj->ni", xf[:, :3, :3], centre) + xf[:, :3, 3]
    we = np.einsum("nij,nj->ni", np.abs(xf[:, :3, :3]), half)
    return np.stack([wc - we, wc + we], axis=1)
