"""Spawned-ray origins: the hit point pushed off its surface by a bound on its own rounding
error, as pbrt-v4 does (Pharr, Jakob, Humphreys, "Physically Based Rendering", 4th ed.,
section 6.8). embreex fixes tnear at 0, so every shadow and bounce ray starts here. This
module is the design note: the formulas run row by row in `nprt.workers.kernels.shade`
(`point_error`, `offset_origin`), and their numpy oracles (`hit_point_error`,
`offset_ray_origin`) live in tests/workers/oracles.py.

Precision design (the image must not depend on where the scene sits or how big it is):

- A hit point is computed from the barycentrics in the instance's local space, in
  float64, then moved to world space by the float64 instance transform.
- Its error is bounded in local space by gamma32(7) * 2 max |v| over the hit triangle's
  local vertex coordinates, on every axis. Embree traces in float32 local space and,
  unlike pbrt's intersector, accepts any t > 0: so the bound must cover the error of
  Embree's t for a ray leaving the triangle (pbrt's deltaT, which grows with the
  triangle's extent around the origin, |v - o| <= 2 max |v|) as well as its float32
  barycentrics and the float32 rounding of the local origin. pbrt's per-axis
  gamma(7) sum |b_i v_i| is 0 on the normal axis of a plane through the origin, and the
  ray would start on its surface.
  The transform to world adds gamma64(3) * (|M| |p| + |t|) and carries the local bound
  through |M| (pbrt's Transform of a Point3fi). A ray is traced by moving its world
  origin back to local space in float64, which adds gamma64(3) * (|M^-1| |o| + |t'|)
  there, carried to world by |M| again.
- The origin is pushed along the geometric normal by d = |n| . error, to the side the
  new ray leaves from, and each coordinate is rounded one float64 step further away.
  The push is relative: about 4e-7 of the local coordinates near the origin, and at
  1e7 from the origin the float64 terms add 2e-9 (a fixed 256 float32 ulps used to be
  16 units at 1e6; a fixed epsilon cannot fit both a 1e-6 and a 1e6 scene).
- Origins travel as float64 (`nprt.workers.wavefront.batch.ORIGIN_DTYPE`): 12 bytes more per ray
  than float32 (80 -> 92 for a RayBatch row, 53 -> 65 for a ShadowRayBatch row).
  Alternatives: float32 world origins snap to ulp/2 (1/256 at 1e5) whatever the offset;
  a float32 origin in the hit instance's space plus its index (+4 bytes) keeps float32
  precision near its own surface, but every traversal step (top-level boxes, other
  instances, proxies, quad lights) needs the world point, so it is rebuilt in float64
  anyway and the precision met is the same; rebasing the whole scene on the camera
  keeps float32 only where the scene is small around the camera. float64 is the
  cheapest that holds at any distance from the camera. bench/render/bench_extremes.py has the
  measured cost.
"""
