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
  const lens = data.lens === undefined || data.lens === null ? null : lensFromDict(data.lens);
  const camera = { c2w: matrix, width, height, fx, fy, cx, cy, lens };
  if (lens) { // border_positions: a lens that folds over inside the image is refused when read, not mid-render
    for (let i = 0; i < width; i++) for (const v of [0.5, height - 0.5]) lensDirection(camera, i + 0.5, v);
    for (let j = 0; j < height; j++) for (const u of [0.5, width - 0.5]) lensDirection(camera, u, j + 0.5);
  }
  return camera;
}

// runtime/lens.py: nerfstudio's radial-tangential distortion inverted by Newton's method, in float64 (doubles here,
// the same operations in the same order: both languages agree to the bit before the float32 cast)
const LENS_MODELS = ["opencv", "fisheye"];
const COEFFICIENTS = ["k1", "k2", "k3", "k4", "p1", "p2"];
const MAX_COEFFICIENT = 1e3, NEWTON_STEPS = 10, SINGULAR = 1e-3, TOLERANCE_PX = 1e-3;

/** Lens.from_dict: a known model, the six coefficients finite within ±MAX_COEFFICIENT (a fisheye's p1, p2 zero). */
function lensFromDict(data) {
  const keys = data !== null && typeof data === "object" && !Array.isArray(data) ? Object.keys(data).sort() : null;
  if (!keys || keys.join() !== ["model", ...COEFFICIENTS].sort().join() || !LENS_MODELS.includes(data.model)) {
    throw new UserError(`a camera's lens must be an object with a model (${LENS_MODELS.join(" or ")}) and ${COEFFICIENTS.join(", ")}`,
      { code: "camera.lens", models: LENS_MODELS });
  }
  const coefficients = COEFFICIENTS.map((key) => checkedFloat(data[key], `lens ${key}`, -MAX_COEFFICIENT, MAX_COEFFICIENT,
    { code: "camera.lens_coefficient", key }));
  if (data.model === "fisheye" && (coefficients[4] || coefficients[5])) {
    throw new UserError("a fisheye lens has no tangential coefficients (p1, p2 must be 0)",
      { code: "camera.lens_coefficient", key: coefficients[4] ? "p1" : "p2" });
  }
  return { model: data.model, coefficients };
}

/** distort and undistort of runtime/lens.py for one point: normalised (xd, yd) -> undistorted [x, y], and whether
 * distorting them lands back within TOLERANCE_PX of the pixel (fx, fy: the focal lengths in pixels). */
function undistortPoint(xd, yd, [k1, k2, k3, k4, p1, p2], fx, fy) {
  let x = xd, y = yd;
  for (let step = 0; step < NEWTON_STEPS; step++) {
    const r = x * x + y * y;
    const d = 1.0 + r * (k1 + r * (k2 + r * (k3 + r * k4)));
    const ex = d * x + 2 * p1 * x * y + p2 * (r + 2 * x * x) - xd;
    const ey = d * y + 2 * p2 * x * y + p1 * (r + 2 * y * y) - yd;
    const dR = k1 + r * (2.0 * k2 + r * (3.0 * k3 + r * 4.0 * k4));
    const dX = 2.0 * x * dR, dY = 2.0 * y * dR;
    const exX = d + dX * x + 2.0 * p1 * y + 6.0 * p2 * x;
    const exY = dY * x + 2.0 * p1 * x + 2.0 * p2 * y;
    const eyX = dX * y + 2.0 * p2 * y + 2.0 * p1 * x;
    const eyY = d + dY * y + 2.0 * p2 * x + 6.0 * p1 * y;
    const denominator = eyX * exY - exX * eyY;
    const taken = Math.abs(denominator) > SINGULAR;
    x = x + (taken ? (ex * eyY - ey * exY) / denominator : 0.0);
    y = y + (taken ? (ey * exX - ex * eyX) / denominator : 0.0);
  }
  const r = x * x + y * y;
  const d = 1.0 + r * (k1 + r * (k2 + r * (k3 + r * k4)));
  const backX = d * x + 2 * p1 * x * y + p2 * (r + 2 * x * x), backY = d * y + 2 * p2 * x * y + p1 * (r + 2 * y * y);
  return [x, y, Math.max(Math.abs(backX - xd) * fx, Math.abs(backY - yd) * fy) <= TOLERANCE_PX];
}

/** lens_directions for pixel position (px, py): camera-space [x, y, z] as doubles; throws where the lens folds over. */
function lensDirection(camera, px, py) {
  const { lens } = camera;
  const [x, yDown, inverted] = undistortPoint((px - camera.cx) / camera.fx, (py - camera.cy) / camera.fy, lens.coefficients,
    camera.fx, camera.fy);
  if (!inverted) {
    throw new UserError(`a ${lens.model} lens (${lens.coefficients.join(", ")}) cannot be undone across a ` +
      `${camera.width}x${camera.height} image: its distortion folds over inside it`, { code: "camera.lens_folds", model: lens.model });
  }
  const y = -yDown;
  if (lens.model === "opencv") return [x, y, -1];
  const theta = Math.min(Math.max(Math.sqrt(x * x + y * y), 0.0), Math.PI);
  const scale = theta > 0 ? Math.sin(theta) / theta : 1.0;
  return [x * scale, y * scale, -Math.cos(theta)];
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
    const at = (p - start) * 3;
    if (camera.lens) {
      // numpy: float32 pixel positions, the lens in float64, its directions cast to float32 before the matmul
      const [lx, ly, lz] = lensDirection(camera, f32(i + pc), f32(j + pc)).map(f32);
      for (let r = 0; r < 3; r++) {
        directions[at + r] = f32(f32(f32(lx * R[3 * r]) + f32(ly * R[3 * r + 1])) + f32(lz * R[3 * r + 2]));
        origins[at + r] = t[r];
      }
      continue;
    }
    const dy = -f32(f32(f32(j + pc) - cy) / fy);
    const dx = f32(f32(f32(i + pc) - cx) / fx);
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
