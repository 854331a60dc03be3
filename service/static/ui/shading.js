// pmvir's per-view shading S(N) (pmvir.sh.sh_basis): the spec's pmvir-sh9 terms of illumination.json's
// "sh", then, where a frame has "sh_high" (refine.lighting.sh_order 3 or 4), the degree-3 and degree-4 terms.

// S(N) at a unit normal (x, y, z) in capture world coordinates.
export function shading(x, y, z, sh, shHigh) {
  let s = sh[0] + sh[1] * y + sh[2] * z + sh[3] * x + sh[4] * x * y + sh[5] * y * z
    + sh[6] * (z * z - 1 / 3) + sh[7] * x * z + sh[8] * (x * x - y * y);
  if (!shHigh || shHigh.length === 0) return s;
  const x2 = x * x, y2 = y * y, z2 = z * z;
  const high = [
    y * (3 * x2 - y2),
    x * y * z * 5.2,
    y * (5 * z2 - 1) * 0.726,
    z * (5 * z2 - 3) / 2,
    x * (5 * z2 - 1) * 0.726,
    z * (x2 - y2) * 2.6,
    x * (x2 - 3 * y2),
    x * y * (x2 - y2) * 4,
    y * z * (3 * x2 - y2) * 3.08,
    x * y * (7 * z2 - 1) * 1.56,
    y * z * (7 * z2 - 3) * 0.947,
    (35 * z2 * z2 - 30 * z2 + 3) / 8,
    x * z * (7 * z2 - 3) * 0.947,
    (x2 - y2) * (7 * z2 - 1) * 0.78,
    x * z * (x2 - 3 * y2) * 3.08,
    x2 * x2 - 6 * x2 * y2 + y2 * y2,
  ];
  for (let k = 0; k < shHigh.length && k < high.length; k++) s += shHigh[k] * high[k];
  return s;
}

// The same at a glTF normal: glTF (x, y, z) -> capture world (x, -z, y), the inverse of
// asset.extras.pmvir.gltf_from_capture.
export function shadingAtGltfNormal(nx, ny, nz, sh, shHigh) {
  return shading(nx, -nz, ny, sh, shHigh);
}
