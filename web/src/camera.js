// Mirrors runtime/camera.py (cameras, ray directions, pixel centres, NDC) and runtime/rays.py (rays in the
// field's space: view directions, then NDC). numpy computes these in float32; here every float32 step is a
// Math.fround in numpy's operation order. The one matmul, pixel_rays' `dirs @ c2w[:3, :3].T`, is a float32
// multiply-add chain over k = 0, 1, 2; numpy's BLAS may fuse it (FMA) where this does not, which moves a
// direction by an ulp at most and no revealed 8-bit value (web/test measures both).

import { UserError } from "./errors.js";
import { checkedFloat, checkedImageSize, num } from "./limits.js";

const f32 = Math.fround;

/** Camera.from_dict: integer size within the caps, finite intrinsics, finite pose. Keys are read in Python's order,
 * each when Python reads it (a missing one: camera.missing_key); the size's and intrinsics' refusals are limits'. */
export function cameraFromDict(data) {
  if (data === null || typeof data !== "object" || Array.isArray(data)) {
    throw new UserError("malformed camera: expected an object", { code: "camera.not_object" });
  }
  const get = (key) => {
    if (!Object.hasOwn(data, key)) throw new UserError(`malformed camera: missing "${key}"`, { code: "camera.missing_key", key });
    return data[key];
  };
  const bad = () => new UserError("malformed camera: c2w must be a finite 4x4 matrix", { code: "camera.bad_c2w" });
  const rows = get("c2w");
  if (!Array.isArray(rows) || !rows.every((row) => Array.isArray(row))) throw bad();
  const values = rows.flat();
  // numpy's array: booleans are numbers beside numbers (and beside the row a 3x4 pose gets), a matrix of them is not
  if (rows.length === 4 && values.length > 0 && values.every((v) => typeof v === "boolean")) throw bad();
  let matrix = rows.map((row) => row.map((v) => {
    const n = typeof v === "boolean" ? Number(v) : num(v);
    if (n === undefined) throw bad();
    return n;
  }));
  if (matrix.length === 3 && matrix.every((row) => row.length === 4)) matrix = [...matrix, [0, 0, 0, 1]];
  if (matrix.length !== 4 || !matrix.every((row) => row.length === 4) || !matrix.flat().every(Number.isFinite)) throw bad();
  const size = [get("width"), get("height")];
  const [width, height] = checkedImageSize(size[0], size[1], "camera", { code: "camera.size" });
  const [fx, fy] = ["fx", "fy"].map((key) => checkedFloat(get(key), `camera ${key}`, 1e-6, 1e9, { code: "camera.focal", key }));
  const [cx, cy] = ["cx", "cy"].map((key) => checkedFloat(get(key), `camera ${key}`, -1e9, 1e9, { code: "camera.center", key }));
  return { c2w: matrix, width, height, fx, fy, cx, cy };
}

/** NDCSpace.from_dict. */
export function ndcFromDict(data) {
  const keys = data && typeof data === "object" && !Array.isArray(data) ? Object.keys(data) : null;
  const allowed = ["tan_half_fov_x", "tan_half_fov_y", "near_plane"];
  if (!keys || !keys.includes("tan_half_fov_x") || !keys.includes("tan_half_fov_y") || !keys.every((k) => allowed.includes(k))) {
    throw new UserError("ndc must be an object with tan_half_fov_x, tan_half_fov_y and near_plane", { code: "camera.bad_ndc" });
  }
  const space = { near_plane: 1.0 };
  for (const [name, value] of Object.entries(data)) space[name] = checkedFloat(value, `ndc ${name}`, 1e-6, 1e6, { code: "camera.ndc_value", key: name });
  return space;
}

/** camera_rays + pixel_rays: world rays of a camera's pixels start..stop (row-major; each pixel's ray is its own,
 * so a range equals that range of the whole camera's). -> {origins, directions} Float32Array ((stop − start)·3). */
export function cameraRays(camera, pixelCenter, start = 0, stop = camera.width * camera.height) {
  const { width } = camera;
  const n = stop - start;
  const origins = new Float32Array(n * 3), directions = new Float32Array(n * 3);
  const R = Float32Array.from(camera.c2w.slice(0, 3).flatMap((row) => row.slice(0, 3)));
  const t = Float32Array.from(camera.c2w.slice(0, 3), (row) => row[3]);
  const pc = f32(pixelCenter), cx = f32(camera.cx), cy = f32(camera.cy), fx = f32(camera.fx), fy = f32(camera.fy);
  for (let p = start; p < stop; p++) {
    const j = Math.floor(p / width), i = p - j * width;
    const dy = -f32(f32(f32(j + pc) - cy) / fy);
    const dx = f32(f32(f32(i + pc) - cx) / fx);
    const at = (p - start) * 3;
    for (let r = 0; r < 3; r++) {
      directions[at + r] = f32(f32(f32(dx * R[3 * r]) + f32(dy * R[3 * r + 1])) - R[3 * r + 2]);
      origins[at + r] = t[r];
    }
  }
  return { origins, directions };
}

/** normalize_directions: unit view directions (float32 norm: squares summed in order, sqrt). */
export function normalizeDirections(directions) {
  const n = directions.length / 3;
  const out = new Float32Array(directions.length);
  for (let k = 0; k < n; k++) {
    const x = directions[3 * k], y = directions[3 * k + 1], z = directions[3 * k + 2];
    const norm = f32(Math.sqrt(f32(f32(f32(x * x) + f32(y * y)) + f32(z * z))));
    if (!(norm > 0)) throw new UserError("a ray has a zero-length direction", { code: "camera.zero_direction" });
    out[3 * k] = f32(x / norm);
    out[3 * k + 1] = f32(y / norm);
    out[3 * k + 2] = f32(z / norm);
  }
  return out;
}

/** ndc_rays: nerf-pytorch's projection, float32 with Python scalars cast to float32 as numpy does. */
export function ndcRays(space, origins, directions) {
  const n = origins.length / 3;
  const o = new Float32Array(origins.length), d = new Float32Array(directions.length);
  const near = f32(space.near_plane);
  const ax = f32(-1.0 / space.tan_half_fov_x), ay = f32(-1.0 / space.tan_half_fov_y);
  const twoNear = f32(2.0 * space.near_plane), minusTwoNear = f32(-2.0 * space.near_plane);
  for (let k = 0; k < n; k++) {
    const [rox, roy, roz] = [origins[3 * k], origins[3 * k + 1], origins[3 * k + 2]];
    const [dx, dy, dz] = [directions[3 * k], directions[3 * k + 1], directions[3 * k + 2]];
    const t = f32(-f32(near + roz) / dz);
    const ox = f32(rox + f32(t * dx)), oy = f32(roy + f32(t * dy)), oz = f32(roz + f32(t * dz));
    o[3 * k] = f32(f32(ax * ox) / oz);
    o[3 * k + 1] = f32(f32(ay * oy) / oz);
    o[3 * k + 2] = f32(1.0 + f32(twoNear / oz));
    d[3 * k] = f32(ax * f32(f32(dx / dz) - f32(ox / oz)));
    d[3 * k + 1] = f32(ay * f32(f32(dy / dz) - f32(oy / oz)));
    d[3 * k + 2] = f32(minusTwoNear / oz);
  }
  return { origins: o, directions: d };
}

/** rays.camera_ray_batch(...).rows(start, stop): the rays of pixels start..stop (default: every pixel) in the
 * field's space -> {origins, directions, viewdirs, length}. */
export function cameraRayBatch(camera, config, start = 0, stop = camera.width * camera.height) {
  const world = cameraRays(camera, config.pixelCenter, start, stop);
  const viewdirs = normalizeDirections(world.directions);
  const rays = config.ndc ? ndcRays(config.ndc, world.origins, world.directions) : world;
  return { origins: rays.origins, directions: rays.directions, viewdirs, length: stop - start };
}
