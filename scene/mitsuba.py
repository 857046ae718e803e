"""Export an nprt scene to Mitsuba 3 (a scene dict for `mitsuba.load_dict`), so a
well-known renderer can check nprt's images and measure its speed per core.

What maps exactly (the two renderers then estimate the same integral):
- base meshes (`mitsuba.Mesh` built in memory, vertex normals and UVs when present) in one
  `shapegroup` each, placed by `instance`s with the float64 transform rounded to Mitsuba's
  float32; two-sided diffuse materials (`twosided` over `diffuse`), with an albedo texture
  as a nearest-texel, repeating `bitmap` (nprt's texel row is (1 - v) * h: v is flipped);
- quad lights as `rectangle`s with a one-sided `area` emitter (corner + a u + b v, facing
  cross(u, v)); point (`point`, intensity W/sr) and directional (`directional`,
  irradiance W/m^2) lights; a constant environment (`constant`);
- the pinhole camera (`perspective`, vertical field of view, near plane at nprt's near
  distance) with a box pixel filter, and nprt's B bounces as `max_depth` B + 1 (Mitsuba
  counts the camera segment), Russian roulette off unless the settings turn it on.

What has no exact equivalent:
- nprt's sky (radiance blended from horizon to zenith by the direction's +y) becomes a
  lat-long `envmap` of SKY_ROWS rows: exact up to its bilinear interpolation between rows
  (relative error below 1e-5 at the default size);
- a quad light's back side: nprt's rays (shadow rays too) pass through it, Mitsuba's
  rectangle blocks them (black), so it casts shadows of other lights; scenes that agree
  keep their quads above everything they light and out of other lights' way;
- emissive meshes: nprt adds their emission on both sides and never samples them;
  Mitsuba's `area` emitter emits on the front only (and samples them). They are exported
  as world-space meshes (emitters cannot live in a shapegroup), exact only where seen
  from the front;
- Russian roulette and the light sampling strategy differ (Mitsuba samples one emitter
  per bounce, nprt S shadow rays): the same integral, not the same estimator.
"""

from __future__ import annotations

import numpy as np

from nprt.scene.model import Environment, Material, Mesh, Scene

MITSUBA_VARIANT = "scalar_rgb"
# Rows of the lat-long map standing in for nprt's sky: the radiance is linear in
# cos(theta), and bilinear rows of pi / SKY_ROWS miss it by at most (pi / rows)^2 / 8.
SKY_ROWS = 1024
SKY_COLS = 8  # the sky does not vary with azimuth


def _mi():
    import mitsuba as mi

    if mi.variant() != MITSUBA_VARIANT:
        mi.set_variant(MITSUBA_VARIANT)
    return mi


def _rgb(x) -> dict:
    return {"type": "rgb", "value": [float(c) for c in x]}


def _bsdf(mi, material: Material, textured: bool) -> dict:
    """Two-sided diffuse, textured where the mesh has UVs (as nprt's surface kernel)."""
    if textured:
        tex = np.ascontiguousarray(material.texture, np.float32)
        reflectance = {"type": "bitmap", "bitmap": mi.Bitmap(tex), "filter_type": "nearest",
                       "wrap_mode": "repeat", "raw": True}
    else:
        reflectance = _rgb(material.albedo)
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance}}


def _mesh(mi, name: str, mesh: Mesh, vertices: np.ndarray, normals, props):
    """A `mitsuba.Mesh` from vertices (v, 3), mesh.faces (f, 3) and optional normals."""
    textured = props is not None and mesh.uvs is not None
    out = mi.Mesh(name, len(vertices), len(mesh.faces), props=props,
                  has_vertex_normals=normals is not None, has_vertex_texcoords=textured)
    params = mi.traverse(out)
    floats, ints = type(params["vertex_positions"]), type(params["faces"])
    params["vertex_positions"] = floats(np.ascontiguousarray(vertices, np.float32).ravel())
    params["faces"] = ints(np.ascontiguousarray(mesh.faces, np.uint32).ravel())
    if normals is not None:
        params["vertex_normals"] = floats(np.ascontiguousarray(normals, np.float32).ravel())
    if textured:
        uv = np.array(mesh.uvs, np.float32)
        uv[:, 1] = 1.0 - uv[:, 1]  # nprt's texel row is (1 - v) * h, Mitsuba's v * h
        params["vertex_texcoords"] = floats(uv.ravel())
    params.update()
    return out


def _base_mesh(mi, i: int, mesh: Mesh, materials) -> object:
    mat = materials[mesh.material]
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf(mi, mat, mat.texture is not None and
                                       mesh.uvs is not None))
    return _mesh(mi, f"mesh{i}_{mesh.name}", mesh, mesh.vertices, mesh.normals, props)


def _emissive_instances(mi, scene: Scene, mesh_index: int) -> dict:
    """World-space copies of an emissive mesh's instances, each an `area` emitter."""
    mesh = scene.meshes[mesh_index]
    mat = scene.materials[mesh.material]
    out = {}
    for j in np.flatnonzero(scene.instances.mesh == mesh_index):
        xf = scene.instances.transform[j]
        v = mesh.vertices.astype(np.float64) @ xf[:3, :3].T + xf[:3, 3]
        n = None
        if mesh.normals is not None:
            n = mesh.normals.astype(np.float64) @ np.linalg.inv(xf[:3, :3])
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(_bsdf(mi, mat, False))
        props["emitter"] = mi.load_dict({"type": "area", "radiance": _rgb(mat.emission)})
        out[f"emissive{j}"] = _mesh(mi, f"emissive{j}", mesh, v, n, props)
    return out


def _quad(mi, q) -> dict:
    """nprt's quad corner + a u + b v (a, b in [0, 1]) as Mitsuba's rectangle [-1, 1]^2
    at z = 0 facing +z: x -> u / 2, y -> v / 2, z -> the unit normal cross(u, v)."""
    u, v = np.asarray(q.edge_u, np.float64), np.asarray(q.edge_v, np.float64)
    n = np.cross(u, v)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = u / 2, v / 2, n / np.linalg.norm(n)
    m[:3, 3] = np.asarray(q.corner, np.float64) + (u + v) / 2
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f(m.tolist()),
            "bsdf": {"type": "diffuse", "reflectance": _rgb((0.0, 0.0, 0.0))},
            "emitter": {"type": "area", "radiance": _rgb(q.radiance)}}


def sky_bitmap(env: Environment) -> np.ndarray:
    """(SKY_ROWS, SKY_COLS, 3) float32 lat-long map of nprt's sky: row i at polar angle
    (i + 0.5) pi / SKY_ROWS from +y (Mitsuba's envmap is y-up, row 0 at the zenith)."""
    theta = (np.arange(SKY_ROWS) + 0.5) * np.pi / SKY_ROWS
    w = np.clip(np.cos(theta), 0.0, 1.0)[:, None]
    rows = (1 - w) * np.asarray(env.horizon)[None] + w * np.asarray(env.zenith)[None]
    return np.ascontiguousarray(np.repeat(rows[:, None, :], SKY_COLS, axis=1), np.float32)


def _environment(mi, env: Environment) -> dict | None:
    if env.kind == "sky":
        return {"type": "envmap", "bitmap": mi.Bitmap(sky_bitmap(env))}
    if env.kind != "constant":
        raise ValueError(f"environment kind {env.kind!r} has no Mitsuba equivalent")
    if max(env.radiance) <= 0:
        return None
    return {"type": "constant", "radiance": _rgb(env.radiance)}


def _sensor(mi, scene: Scene, width: int, height: int, spp: int, seed: int) -> dict:
    cam = scene.camera
    lo, hi = _scene_bounds(scene)
    far = 10.0 * (np.linalg.norm(hi - lo) + np.linalg.norm(np.asarray(cam.eye) - lo)) + 1.0
    return {
        "type": "perspective", "fov": float(cam.fov_deg), "fov_axis": "y",
        "near_clip": float(cam.near_distance), "far_clip": float(far),
        "to_world": mi.ScalarTransform4f().look_at(
            origin=[float(x) for x in cam.eye], target=[float(x) for x in cam.target],
            up=[float(x) for x in cam.up]),
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb",
                 "component_format": "float32"},
    }


def _scene_bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    from nprt.scene.model import instance_world_bounds

    b = instance_world_bounds(scene)  # (m, 2, 3)
    if len(b) == 0:
        return np.zeros(3), np.ones(3)
    return b[:, 0].min(axis=0), b[:, 1].max(axis=0)


def to_mitsuba(scene: Scene, *, width: int, height: int, spp: int, bounces: int,
               seed: int = 0, russian_roulette: bool = False) -> dict:
    """The scene dict for `mitsuba.load_dict` (variant MITSUBA_VARIANT): see the module
    docstring for what maps exactly. width, height in pixels; spp samples per pixel;
    bounces nprt's B."""
    mi = _mi()
    if spp < 1 or width < 1 or height < 1 or bounces < 0:
        raise ValueError(f"to_mitsuba: need width, height, spp >= 1 and bounces >= 0, got "
                         f"{width}x{height}, spp={spp}, bounces={bounces}")
    d: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": int(bounces) + 1,
                       "rr_depth": 3 if russian_roulette else int(bounces) + 2,
                       "hide_emitters": False},
        "sensor": _sensor(mi, scene, width, height, spp, seed),
    }
    emissive = {i for i, m in enumerate(scene.meshes)
                if scene.materials[m.material].is_emissive}
    used = set(np.unique(scene.instances.mesh).tolist()) - emissive
    for i in sorted(used):
        # A shapegroup must be a child of the scene itself; instances name it by id.
        d[f"group{i}"] = {"type": "shapegroup",
                          "mesh": _base_mesh(mi, i, scene.meshes[i], scene.materials)}
        for j in np.flatnonzero(scene.instances.mesh == i):
            d[f"instance{j}"] = {"type": "instance",
                                 "shapegroup": {"type": "ref", "id": f"group{i}"},
                                 "to_world": mi.ScalarTransform4f(
                                     scene.instances.transform[j].tolist())}
    for i in sorted(emissive):
        d.update(_emissive_instances(mi, scene, i))
    for k, q in enumerate(scene.quad_lights):
        d[f"quad{k}"] = _quad(mi, q)
    for k, p in enumerate(scene.point_lights):
        d[f"point{k}"] = {"type": "point", "position": [float(x) for x in p.position],
                          "intensity": _rgb(p.intensity)}
    for k, dl in enumerate(scene.directional_lights):
        d[f"directional{k}"] = {"type": "directional",
                                "direction": [float(x) for x in dl.direction],
                                "irradiance": _rgb(dl.irradiance)}
    env = _environment(mi, scene.environment)
    if env is not None:
        d["environment"] = env
    return d


def render_mitsuba(scene: Scene, *, width: int, height: int, spp: int, bounces: int,
                   seed: int = 0, threads: int = 1) -> np.ndarray:
    """Render with Mitsuba 3 (MITSUBA_VARIANT) on `threads` threads; returns the
    (height, width, 3) float64 image, linear radiance like nprt's `Film.image`."""
    mi = _mi()
    import drjit as dr

    dr.set_thread_count(int(threads))
    loaded = mi.load_dict(to_mitsuba(scene, width=width, height=height, spp=spp,
                                     bounces=bounces, seed=seed))
    return np.array(mi.render(loaded, spp=spp, seed=seed), np.float64)
