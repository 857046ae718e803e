"""The JSON scene file format as pydantic v2 models, with its constraints on the fields.

`nprt.scene.json_load` and `nprt.scene.json_save` read and write these and convert them to
and from `nprt.scene.model.Scene`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, model_validator

FORMAT_VERSION = 1

Finite = Annotated[float, Field(allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
Unit = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0.0, allow_inf_nan=False)]
Vec3 = tuple[Finite, Finite, Finite]
Color = tuple[NonNeg, NonNeg, NonNeg]
Albedo = tuple[Unit, Unit, Unit]
Index = Annotated[int, Field(ge=0)]
Row4 = tuple[Finite, Finite, Finite, Finite]
# A mesh or material is referenced by its name, or by its position when names repeat.
Ref = str | Index


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MaterialSpec(_Strict):
    """Diffuse material; `texture` is an image (PNG/JPEG, sRGB) or a .npy (linear float32)
    relative to the scene file."""

    name: str = Field(min_length=1)
    albedo: Albedo = (0.8, 0.8, 0.8)
    emission: Color = (0.0, 0.0, 0.0)
    texture: str | None = Field(default=None, min_length=1)


class MeshSpec(_Strict):
    """A base mesh from a file (OBJ/PLY/STL/GLB/glTF relative to the scene file), or inline."""

    name: str = Field(min_length=1)
    path: str | None = Field(default=None, min_length=1)
    vertices: list[Vec3] | None = None
    faces: list[tuple[Index, Index, Index]] | None = None
    normals: list[Vec3] | None = None
    uvs: list[tuple[Finite, Finite]] | None = None
    material: Ref | None = None

    @model_validator(mode="after")
    def _one_source(self) -> MeshSpec:
        inline = self.vertices is not None or self.faces is not None
        if self.path is not None and inline:
            raise ValueError("give either 'path' or inline 'vertices'/'faces', not both")
        if self.path is None and (self.vertices is None or self.faces is None):
            raise ValueError("needs a 'path' or both inline 'vertices' and 'faces'")
        if self.path is not None and (self.normals is not None or self.uvs is not None):
            raise ValueError("inline 'normals'/'uvs' are only allowed with inline vertices")
        return self


class _PoseSpec(_Strict):
    """A pose: a 4x4 row-major `transform`, or translate/rotate/scale composed as
    T @ R @ S with `rotate_deg` Euler angles applied about x, then y, then z."""

    transform: tuple[Row4, Row4, Row4, Row4] | None = None
    translate: Vec3 | None = None
    rotate_deg: Vec3 | None = None
    scale: Finite | Vec3 | None = None

    @model_validator(mode="after")
    def _one_form(self) -> _PoseSpec:
        trs = self.translate is not None or self.rotate_deg is not None or self.scale is not None
        if self.transform is not None and trs:  # no generator: runs once per instance
            raise ValueError("give either 'transform' or translate/rotate_deg/scale, not both")
        return self


class InstanceSpec(_PoseSpec):
    """A placement of mesh `mesh` (the pose fields of `_PoseSpec`)."""

    mesh: Ref


class InstanceFileSpec(_Strict):
    """Every instance as arrays in a NumPy `.npz` file relative to the scene file (read by
    `nprt.scene.instances`): `mesh` (m,) integer, indices into `meshes`; `transform` (m, 4, 4)
    float, each a row-major affine local -> world matrix as in `InstanceSpec.transform`.
    No other arrays. Loads in milliseconds where one JSON object per instance takes
    seconds per hundred thousand."""

    file: str = Field(min_length=1)


def _instances_form(value) -> str:
    """The union member: JSON objects (and specs being dumped) are the file form."""
    return "array-file" if isinstance(value, dict | InstanceFileSpec) else "list"


# A list of InstanceSpec, or {"file": ...}. The tags are dropped from error paths by
# nprt.scene.json_load (a tag that is not an identifier never shows), so errors read
# instances[3].mesh.
InstancesSpec = Annotated[
    Annotated[list[InstanceSpec], Field(min_length=1), Tag("list")]
    | Annotated[InstanceFileSpec, Tag("array-file")],
    Discriminator(_instances_form),
]


class QuadLightSpec(_Strict):
    """Parallelogram corner + a*edge_u + b*edge_v, emitting along cross(edge_u, edge_v)."""

    corner: Vec3
    edge_u: Vec3
    edge_v: Vec3
    radiance: Color


class PointLightSpec(_Strict):
    position: Vec3
    intensity: Color


class DirectionalLightSpec(_Strict):
    """`direction` is the direction the light travels."""

    direction: Vec3
    irradiance: Color


class LightsSpec(_Strict):
    quads: list[QuadLightSpec] = []
    points: list[PointLightSpec] = []
    directionals: list[DirectionalLightSpec] = []


class EnvironmentSpec(_Strict):
    kind: Literal["constant", "sky"] = "constant"
    radiance: Color = (0.0, 0.0, 0.0)
    zenith: Color = (0.0, 0.0, 0.0)
    horizon: Color = (0.0, 0.0, 0.0)


class CameraSpec(_Strict):
    """`near`: distance of the near plane along the view axis (glTF's znear); surfaces
    before it are not seen. Unset: 1e-5 of the eye-to-target distance."""

    eye: Vec3 = (0.0, 0.0, 5.0)
    target: Vec3 = (0.0, 0.0, 0.0)
    up: Vec3 = (0.0, 1.0, 0.0)
    fov_deg: float = Field(default=45.0, gt=0.0, lt=180.0)
    near: float | None = Field(default=None, ge=0.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _well_posed(self) -> CameraSpec:
        view = [t - e for t, e in zip(self.target, self.eye, strict=True)]
        if not any(view):
            raise ValueError("'eye' and 'target' coincide")
        u = self.up
        cross = (view[1] * u[2] - view[2] * u[1], view[2] * u[0] - view[0] * u[2],
                 view[0] * u[1] - view[1] * u[0])
        if not any(cross):
            raise ValueError("'up' is zero or parallel to the viewing direction")
        return self


class InstanceKeySpec(_PoseSpec):
    """One key of an instance's track: its pose on `frame` (a `transform` without shear,
    or translate/rotate_deg/scale; unset parts are identity)."""

    frame: Index


class LightKeySpec(_Strict):
    """One key of a light's track: the fields it sets on `frame` (those of the light's kind:
    quads corner/edge_u/edge_v/radiance, points position/intensity, directionals
    direction/irradiance); a field no key sets keeps the light's own value."""

    frame: Index
    corner: Vec3 | None = None
    edge_u: Vec3 | None = None
    edge_v: Vec3 | None = None
    radiance: Color | None = None
    position: Vec3 | None = None
    intensity: Color | None = None
    direction: Vec3 | None = None
    irradiance: Color | None = None


class LightTracksSpec(_Strict):
    """Tracks by light index (a JSON object key, "0") within each kind of `lights`."""

    quads: dict[Index, Annotated[list[LightKeySpec], Field(min_length=1)]] = {}
    points: dict[Index, Annotated[list[LightKeySpec], Field(min_length=1)]] = {}
    directionals: dict[Index, Annotated[list[LightKeySpec], Field(min_length=1)]] = {}


class AnimationSpec(_Strict):
    """Frames 0 .. frames-1. `instances`: tracks by instance index (a JSON object key,
    "3"); `lights`: tracks by light. Keys of a track have strictly increasing frames;
    between keys values are interpolated (`linear`: positions, scales and light fields
    lerp, rotations slerp along the shorter arc; `step`: the earlier key holds), and
    before the first key or after the last the end key holds. Instances and lights
    without a track keep their pose in the scene on every frame; the scene as loaded is
    frame 0."""

    frames: int = Field(ge=1, le=100_000)
    interpolation: Literal["linear", "step"] = "linear"
    instances: dict[Index, Annotated[list[InstanceKeySpec], Field(min_length=1)]] = {}
    lights: LightTracksSpec = LightTracksSpec()


class SceneFile(_Strict):
    """The whole scene file."""

    version: Literal[1] = FORMAT_VERSION
    name: str = "scene"
    materials: list[MaterialSpec] = []
    meshes: list[MeshSpec] = Field(min_length=1)
    instances: InstancesSpec
    lights: LightsSpec = LightsSpec()
    environment: EnvironmentSpec = EnvironmentSpec()
    camera: CameraSpec = CameraSpec()
    animation: AnimationSpec | None = None
