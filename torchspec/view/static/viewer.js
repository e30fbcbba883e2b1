// torchspec view: relights SVBRDF maps with the fit's model (Lambert + Ward, one or two lobes,
// isotropic or anisotropic) under a point light, per pixel, in WebGL2. Plain JavaScript, no
// network beyond the site's own files (manifest.json, tiles/, photo/): see torchspec/view/site.py.
// The shading repeats torchspec.rendering.render's point path (torchspec/lobe.py lobe_at,
// torchspec/diffuse.py): value = k_d / pi <n, l>^+ + k_s W(l) + k_s2 W2(l), times the exposure.
// Under a capture's extended light kernel, the weighted sum of that value over the kernel's fixed
// quadrature nodes about the light's centre (manifest kernel_nodes: torchspec/view/light.py).
// A fit's residual term (manifest term: its basis functions; the tiles' term textures), on the
// "relit" layer, as torchspec.residual_term.ResidualTerm.apply adds it at unit light:
// decode(w encode(value) + sum_j c_j H_j(d)), d the light's direction (an extended kernel's
// effective direction), encode the photographs' encoding (manifest term_encoding: sRGB, or the
// capture's estimated camera response: torchspec.residual_term.TermDomain); the "physical" layer
// leaves it off.
// A near light (manifest positions, near_radius; the distance control) lights each texel as
// torchspec/near_lights.py does: from (p - x) / |p - x| with the falloff (|p| / |p - x|)^2, x the
// centre of the texel's block of torchspec.relight.render_near (or, asked, of the pixel itself):
// render's block of the capture's positions (manifest near_block) for a frame's own position, else
// render's block of that one light (Viewer.renderBlock, the rule torchspec.pipeline.tiling.near_block);
// an extended kernel about that direction, and the residual term at it.
// Maps with a height (manifest shadows; the tiles' shadow textures: horizon maps and the indirect
// share, torchspec/view/shadows.py) cast shadows, as torchspec.relight.shaded_render does:
// term(V r) + b D, V = sigmoid((e - H) / s) with the horizon H interpolated between the maps'
// azimuths, s the fit's penumbra widened by an extended kernel's spread in elevation
// (torchspec.model.visibility's probit rule), D the flat diffuse; a near light's V from each
// pixel's own direction (torchspec.model.visibility.frame_visibility).
"use strict";

const LAYERS = ["relit", "normal", "diffuse", "specular", "roughness", "model", "quality", "flags", "std", "photo", "physical"];
const PHOTO_LAYER = 9;
const TILE_UNITS = 6; // a map tile's first textures' units (then the photograph's, then the term's)
const SHADOW_UNIT = 14; // the cast shadows' texture array (after the term's seven)
const MAX_TILES = 160; // textures kept on the GPU (least recently used dropped)
const MAX_FETCHES = 6;
const INTERACTIVE_MS = 250; // input this recent: frames at a reduced scale
const FRAME_MS = 40; // the frame time a reduced scale aims at
const TILE_FRAME_MS = 300; // while tiles arrive, a frame at most this often
const RETRY_MS = 500; // a tile the server has not made yet (503: its level's pass still runs): asked again after

const VERTEX = `#version 300 es
uniform vec4 uRect;
out vec2 vTex;
uniform float uTile;
void main() {
  vec2 c = vec2(float(gl_VertexID & 1), float(gl_VertexID >> 1));
  vTex = c * uTile;
  gl_Position = vec4(mix(uRect.xy, uRect.zw, c), 0.0, 1.0);
}`;

const FRAGMENT = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
uniform sampler2D tGeo, tRough, tKd, tKs, tKs2, tStd, tPhoto;
uniform ivec2 uValid;
uniform int uLayer, uStd, uUntrusted, uModels;
#if EXTENDED // the program of an extended light (the point light's compiles without it)
uniform int uNodes, uAngular; // the extended light's nodes; angular offsets
uniform vec3 uNode[64]; // each node's offset from the centre (x, y) and weight
uniform float uSigma; // > 0: a projected Gaussian kernel's std: its lobes on the rule uLobeRule
uniform int uLobeNodes;
uniform vec3 uLobeRule[16]; // standard normal Gauss-Hermite points (x, y) and weights
uniform int uDiffuseRows; // > 0: the kernel's effective diffuse direction, tabulated over |l_xy| of the centre
uniform float uDiffuseReach;
uniform vec4 uDiffuse[64]; // rows 2i and 2i + 1: (a, b) of d = (a l_xy / |l_xy|, b)
#endif
#if TERM // the residual term's basis functions (4 or 9): its weight and coefficients, packed
uniform sampler2D tTerm0, tTerm1, tTerm2, tTerm3, tTerm4, tTerm5, tTerm6;
#if CURVE // its encoding, a camera response (torchspec.response.ResponseCurve) per channel
uniform vec3 uGamma, uOffset, uContrast, uSlope; // uSlope: the curve's slope at code 1
#endif
#endif
#if SHADOWS // horizon maps (SHADOWS azimuths, four a layer) and the indirect share (the next layer, x)
uniform highp sampler2DArray tShadow;
uniform int uShadows; // 1: cast shadows on
uniform float uSoftness; // the fit's penumbra, radians
uniform mat2 uKernelCov; // the kernel's l-plane covariance at the zenith (0: a point)
uniform vec2 uKernelOffset; // its mean's offset from the centre
uniform int uKernelAngular; // 1: the covariance squeezed along the radius by 1 - |c_xy|^2 (an angular kernel)
#endif
uniform vec3 uLight, uView, uModelColours[8];
uniform vec4 uNear; // a near light: its position (image widths from the image's centre) and w = 1; w = 0: distant
uniform vec3 uPlace; // the tile's first texel in level-0 pixels (x, y) and a texel's size in them (z)
uniform ivec2 uSize; // the image's width and height (level-0 pixels)
uniform int uBlock; // a near light's direction is taken at the centre of blocks of this many pixels a side
vec3 gLight; // the light's (centre) direction at this texel: uLight, or towards a near light (lightAt)
uniform float uExposure, uGain, uPhotoScale; // uPhotoScale: a photograph's tile's scale (its JPEG's comment)
in vec2 vTex;
out vec4 outColour;
const float PI = 3.14159265358979;

float ward(vec3 l, vec3 n, vec3 s, vec3 t, float ax, float ay, float ci, float co) {
  if (ci <= 0.0 || co <= 0.0 || ax <= 0.0 || ay <= 0.0 || l.z <= 0.0) return 0.0;
  vec3 h = l + uView;
  float hn = dot(n, h);
  float hs = dot(s, h) / ax, ht = dot(t, h) / ay;
  return exp(-(hs * hs + ht * ht) / (hn * hn)) * sqrt(ci / co) * (1.0 / (4.0 * PI * ax * ay));
}

#if EXTENDED
// The product of the kernel N(gLight.xy, uSigma^2) and a Gaussian N(b, B) in the l-plane: its mean
// (returned) and covariance (cov).
vec2 product(vec2 b, mat2 B, out mat2 cov) {
  float s2 = uSigma * uSigma;
  mat2 gain = s2 * inverse(mat2(s2) + B);
  cov = gain * B;
  return gLight.xy + gain * (b - gLight.xy);
}

// A lobe under a projected Gaussian kernel, on render's Gauss-Hermite points placed on the
// product of the kernel and the lobe in the l-plane, as torchspec/nodes.py's fast rule places
// them (_pairs): the lobe linearised about its mirror point (torchspec/lobe.py lobe_moments),
// then again about that product's mean (slope_at), where the integrand's mass is. A narrow lobe
// falls between fixed nodes, never between these.
float lobeUnderKernel(vec3 n, vec3 s, vec3 t, float ax, float ay, float co) {
  if (ax <= 0.0 || ay <= 0.0 || co <= 0.0) return 0.0;
  float vs = dot(uView, s), vt = dot(uView, t), s2 = uSigma * uSigma;
  vec2 ds = 2.0 * (vs * n.xy + co * s.xy), dt = 2.0 * (vt * n.xy + co * t.xy);
  mat2 lobe = outerProduct(ds, ds) * (0.5 * ax * ax) + outerProduct(dt, dt) * (0.5 * ay * ay), cov;
  vec2 mean = product(2.0 * co * n.xy - uView.xy, lobe, cov);
  // The half vector's slopes (u, v) at the first mean l0 (pulled inside radius 0.98) and their
  // Jacobian J: the lobe about l0 is N(l0 - J^-1 (u, v), J^-1 diag(ax^2, ay^2) / 2 J^-T).
  vec2 l0 = mean * min(1.0, 0.98 / max(length(mean), 1e-30));
  float lz = sqrt(max(1.0 - dot(l0, l0), 1e-12));
  vec3 h = vec3(l0, lz) + uView;
  float hn = dot(n, h);
  if (hn > 0.05 * length(h)) {
    float u = dot(s, h) / hn, v = dot(t, h) / hn;
    vec2 gr = l0 / lz;
    vec2 du = (s.xy - u * n.xy - (s.z - u * n.z) * gr) / hn, dv = (t.xy - v * n.xy - (t.z - v * n.z) * gr) / hn;
    mat2 J = mat2(du.x, dv.x, du.y, dv.y); // rows du, dv
    if (abs(determinant(J)) > 0.0) {
      mat2 inv = inverse(J);
      mean = product(l0 - inv * vec2(u, v), inv * mat2(0.5 * ax * ax, 0.0, 0.0, 0.5 * ay * ay) * transpose(inv), cov);
    }
  }
  float l11 = sqrt(max(cov[0][0], 0.0));
  float l21 = l11 > 0.0 ? cov[0][1] / l11 : 0.0;
  float l22 = sqrt(max(cov[1][1] - l21 * l21, 0.0));
  float area = l11 * l22 / s2, sum = 0.0;
  for (int q = 0; q < 16; q++) {
    if (q >= uLobeNodes) break;
    vec2 xi = uLobeRule[q].xy;
    vec2 p = mean + vec2(l11 * xi.x, l21 * xi.x + l22 * xi.y);
    float r2 = dot(p, p);
    if (r2 >= 1.0) continue; // at or beyond the horizon: no light
    vec3 l = vec3(p, sqrt(1.0 - r2));
    vec2 d = (p - gLight.xy) / uSigma;
    // weight / the standard normal density at xi, times the kernel's density at p and det L
    sum += uLobeRule[q].z * area * exp(0.5 * (dot(xi, xi) - dot(d, d))) * ward(l, n, s, t, ax, ay, dot(n, l), co);
  }
  return sum;
}

// Node q's direction about the light's centre (its z <= 0: at or beyond the horizon, no light).
vec3 nodeDirection(int q, vec3 e1, vec3 e2) {
  vec3 node = uNode[q];
  if (uAngular != 0) {
    float g = length(node.xy);
    return g > 0.0 ? cos(g) * gLight + (sin(g) / g) * (node.x * e1 + node.y * e2) : gLight;
  }
  vec2 p = gLight.xy + node.xy;
  float r2 = dot(p, p);
  return vec3(p, r2 < 1.0 ? sqrt(1.0 - r2) : 0.0);
}

// The kernel's effective diffuse direction at the light's centre, interpolated in its table.
vec3 effective() {
  float rho = length(gLight.xy), f = clamp(rho / uDiffuseReach, 0.0, 1.0) * float(uDiffuseRows - 1);
  int i = min(int(f), uDiffuseRows - 2);
  vec4 a = uDiffuse[i / 2], b = uDiffuse[(i + 1) / 2];
  vec2 lo = i % 2 == 0 ? a.xy : a.zw, hi = i % 2 == 0 ? b.zw : b.xy;
  vec2 d = mix(lo, hi, f - float(i));
  return vec3(rho > 0.0 ? d.x * gLight.xy / rho : vec2(0.0), d.y);
}
#endif

// The near light at texel ij (torchspec/near_lights.py): sets gLight to its direction from the
// centre of the texel's block (the square blocks of uBlock pixels of torchspec.relight.render_near,
// the last ones narrower; 1: the pixel's own centre) and returns its falloff (|p| / |p - x|)^2.
// A distant light: uLight, 1.
float lightAt(ivec2 ij) {
  gLight = uLight;
  if (uNear.w == 0.0) return 1.0;
  ivec2 pixel = min(ivec2(floor(uPlace.xy + (vec2(ij) + 0.5) * uPlace.z)), uSize - 1); // the level-0 pixel at the texel's centre
  ivec2 first = pixel / uBlock * uBlock, stop = min(first + uBlock, uSize);
  vec2 centre = 0.5 * vec2(first + stop); // the mean of the block's pixel centres
  vec3 x = vec3(centre.x / float(uSize.x) - 0.5, (0.5 * float(uSize.y) - centre.y) / float(uSize.x), 0.0);
  vec3 d = uNear.xyz - x;
  gLight = normalize(d);
  return dot(uNear.xyz, uNear.xyz) / dot(d, d);
}

#if SHADOWS
// The horizon (radians) at texel ij along azimuth phi, linear between the maps' two azimuths about it.
float horizonAt(ivec2 ij, float phi) {
  float f = mod(phi * float(SHADOWS) / (2.0 * PI), float(SHADOWS));
  int j0 = min(int(f), SHADOWS - 1), j1 = (j0 + 1) % SHADOWS;
  float a = texelFetch(tShadow, ivec3(ij, j0 / 4), 0)[j0 % 4], b = texelFetch(tShadow, ivec3(ij, j1 / 4), 0)[j1 % 4];
  return mix(a, b, f - float(j0));
}

// The light's visibility at texel ij (torchspec.model.visibility): sigmoid((e - H) / s) of its
// elevation e against the horizon H along its azimuth. A distant light under an extended kernel:
// e and the azimuth of the kernel's mean, s widened by its spread in elevation (the probit rule of
// kernel_visibility); a near light: the direction from the pixel's own centre, s the penumbra.
float seen(ivec2 ij) {
  vec3 w = gLight;
  float s2 = uSoftness * uSoftness;
  if (uNear.w != 0.0) {
    ivec2 pixel = min(ivec2(floor(uPlace.xy + (vec2(ij) + 0.5) * uPlace.z)), uSize - 1);
    vec2 centre = vec2(pixel) + 0.5;
    w = normalize(uNear.xyz - vec3(centre.x / float(uSize.x) - 0.5, (0.5 * float(uSize.y) - centre.y) / float(uSize.x), 0.0));
  } else if (uKernelCov[0][0] + uKernelCov[1][1] > 0.0) {
    vec2 l = w.xy + uKernelOffset;
    float r = length(l), wz2 = max(1.0 - r * r, 1e-6);
    vec2 u = r > 0.0 ? l / r : vec2(0.0);
    float radial = r > 0.0 ? dot(u, uKernelCov * u) : 0.5 * (uKernelCov[0][0] + uKernelCov[1][1]);
    if (uKernelAngular != 0) radial *= 1.0 - dot(w.xy, w.xy);
    s2 += (PI / 8.0) * radial / wz2;
    w = vec3(l, sqrt(wz2));
  }
  float across = length(w.xy), e = atan(w.z, across);
  // the azimuth, from |y| and its sign: SwiftShader's atan(-0.0, x) is +-pi whatever x's sign (a
  // light at 180 degrees took the horizon at 0, at 0 degrees the one at 180)
  float phi = across <= 0.0 ? 0.0 : atan(abs(w.y), w.x) * (w.y < 0.0 ? -1.0 : 1.0);
  return 1.0 / (1.0 + exp(-(e - horizonAt(ij, phi)) / sqrt(s2)));
}

// The flat diffuse's cosine (torchspec.model.indirect.flat_maps rendered: the normal (0, 0, 1),
// no lobe) under the light: l_z, or under an extended kernel as relit() takes a flat normal's.
float flatCosine() {
#if EXTENDED
  if (uDiffuseRows > 0) return max(effective().z, 0.0);
  vec3 e1 = normalize(vec3(1.0, 0.0, 0.0) - gLight.x * gLight), e2 = cross(gLight, e1);
  float front = 0.0;
  for (int q = 0; q < 64; q++) {
    if (q >= uNodes) break;
    vec3 l = nodeDirection(q, e1, e2);
    if (l.z > 0.0) front += uNode[q].z * l.z;
  }
  return front;
#else
  return max(gLight.z, 0.0);
#endif
}
#endif

vec3 srgb(vec3 v) {
  v = clamp(v, 0.0, 1.0);
  return mix(12.92 * v, 1.055 * pow(v, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), v));
}

vec3 relit(ivec2 ij) {
  vec4 g = texelFetch(tGeo, ij, 0), r = texelFetch(tRough, ij, 0);
  vec3 n = g.xyz;
  vec3 s = vec3(1.0, 0.0, 0.0) - n.x * n;
  if (dot(s, s) < 1e-12) s = vec3(0.0, 1.0, 0.0) - n.y * n;
  s = s * inversesqrt(dot(s, s));
  vec3 t = cross(n, s);
  float c = cos(g.w), si = sin(g.w);
  vec3 s2 = c * s + si * t, t2 = c * t - si * s;
  float co = dot(n, uView);
  vec3 kd = texelFetch(tKd, ij, 0).rgb / PI, ks = texelFetch(tKs, ij, 0).rgb, ks2 = texelFetch(tKs2, ij, 0).rgb;
#if !EXTENDED
  float ci = dot(n, gLight);
  return kd * max(ci, 0.0) + ks * ward(gLight, n, s2, t2, r.x, r.y, ci, co) + ks2 * ward(gLight, n, s2, t2, r.z, r.w, ci, co);
#else
  vec3 e1 = normalize(vec3(1.0, 0.0, 0.0) - gLight.x * gLight), e2 = cross(gLight, e1);
  vec3 value = vec3(0.0);
  float front = 0.0, behind = 0.0; // the nodes' cosine in front of the normal's horizon and behind it
  // With the table and render's rule for the lobes, the nodes matter only where the normal's
  // horizon passes within HORIZON_MARGIN kernel widths of the centre (torchspec/diffuse.py).
  vec2 slope = n.xy - n.z * gLight.xy / gLight.z; // the gradient of <n, w(l)> at the centre
  bool clear = uDiffuseRows > 0 && uSigma > 0.0 && dot(n, gLight) > 5.5 * uSigma * length(slope);
  for (int q = 0; q < 64; q++) {
    if (q >= uNodes || clear) break;
    vec3 l = nodeDirection(q, e1, e2);
    if (l.z <= 0.0) continue; // at or beyond the horizon: no light
    float ci = dot(n, l), weight = uNode[q].z;
    front += weight * max(ci, 0.0);
    behind += weight * max(-ci, 0.0);
    if (uSigma <= 0.0) value += weight * (ks * ward(l, n, s2, t2, r.x, r.y, ci, co) + ks2 * ward(l, n, s2, t2, r.z, r.w, ci, co));
  }
  if (uSigma > 0.0) value += ks * lobeUnderKernel(n, s2, t2, r.x, r.y, co) + ks2 * lobeUnderKernel(n, s2, t2, r.z, r.w, co);
  // The diffuse term: with the table, torchspec/diffuse.py's rule: the effective direction's
  // cosine plus the part behind the normal's horizon where most of the kernel is in front, else
  // the part in front (the smaller integral on the nodes).
  float linear = uDiffuseRows > 0 ? dot(n, effective()) : -1.0;
  value += kd * (linear >= 0.0 ? linear + behind : front);
  return value;
#endif
}

#if TERM
// The direction the residual term is a function of (torchspec.residual_term.term_directions): the
// light's, or an extended kernel's effective direction: the table's, else the nodes' sum
// (torchspec.lights.diffuse_directions; not of unit length).
vec3 termDirection() {
#if !EXTENDED
  return gLight;
#else
  if (uDiffuseRows > 0) return effective();
  vec3 e1 = normalize(vec3(1.0, 0.0, 0.0) - gLight.x * gLight), e2 = cross(gLight, e1), d = vec3(0.0);
  for (int q = 0; q < 64; q++) {
    if (q >= uNodes) break;
    vec3 l = nodeDirection(q, e1, e2);
    if (l.z > 0.0) d += uNode[q].z * l;
  }
  return d;
#endif
}

#if CURVE
// torchspec.residual_term.TermDomain with a camera response: torchspec.response's g (codes to
// linear) and its closed-form inverse (invert_curve) on [0, 1], odd below 0 and continued along
// the slope at code 1 above 1.
vec3 logistic(vec3 x) { return 1.0 / (1.0 + exp(-x)); }

vec3 curveDecode(vec3 v) {
  vec3 still = step(abs(uContrast), vec3(1e-3)), m = max(abs(uContrast), vec3(1e-3));
  vec3 low = logistic(-m / 2.0), high = logistic(m / 2.0);
  vec3 p = clamp(low + v * (high - low), 1e-6, 1.0 - 1e-6);
  vec3 up = 0.5 + log(p / (1.0 - p)) / m, un = (logistic(m * (v - 0.5)) - low) / (high - low);
  vec3 u = clamp(mix(mix(un, up, step(0.0, uContrast)), v, still), 0.0, 1.0);
  vec3 h0 = pow(max(uOffset / (1.0 + uOffset), 1e-30), uGamma);
  return (pow(max((u + uOffset) / (1.0 + uOffset), 1e-30), uGamma) - h0) / (1.0 - h0);
}

vec3 curveEncode(vec3 y) {
  vec3 still = step(abs(uContrast), vec3(1e-3)), m = max(abs(uContrast), vec3(1e-3));
  vec3 low = logistic(-m / 2.0), high = logistic(m / 2.0);
  vec3 h0 = pow(max(uOffset / (1.0 + uOffset), 1e-30), uGamma);
  vec3 u = clamp((1.0 + uOffset) * pow(max(h0 + y * (1.0 - h0), 0.0), 1.0 / uGamma) - uOffset, 0.0, 1.0);
  vec3 z = clamp(low + u * (high - low), 1e-6, 1.0 - 1e-6);
  vec3 vp = (logistic(m * (u - 0.5)) - low) / (high - low), vn = 0.5 + log(z / (1.0 - z)) / m;
  return clamp(mix(mix(vn, vp, step(0.0, uContrast)), u, still), 0.0, 1.0);
}

vec3 encode(vec3 v) {
  vec3 a = abs(v);
  return sign(v) * mix(curveEncode(min(a, 1.0)), 1.0 + (a - 1.0) / uSlope, step(vec3(1.0), a));
}

vec3 decode(vec3 e) {
  vec3 a = abs(e);
  return sign(e) * mix(curveDecode(min(a, 1.0)), 1.0 + (a - 1.0) * uSlope, step(vec3(1.0), a));
}
#else
// torchspec.residual_term.encode and decode: the sRGB transfer extended to every real value (at
// the knee either side: the two agree there).
vec3 encode(vec3 v) {
  vec3 a = abs(v);
  return sign(v) * mix(12.92 * a, 1.055 * pow(max(a, 0.0031308), vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), a));
}

vec3 decode(vec3 e) {
  vec3 a = abs(e), knee = vec3(12.92 * 0.0031308);
  return sign(e) * mix(a / 12.92, pow((max(a, knee) + 0.055) / 1.055, vec3(2.4)), step(knee, a));
}
#endif

// The physical value at unit light with the pixel's residual term (ResidualTerm.apply): the
// hemispherical harmonics of torchspec.residual_term.hsh_basis at d (phi's cosine and sine from d's
// x and y: atan2's 0 where both are 0).
vec3 withTerm(ivec2 ij, vec3 value) {
  vec4 p[7];
  p[0] = texelFetch(tTerm0, ij, 0);
  p[1] = texelFetch(tTerm1, ij, 0);
  p[2] = texelFetch(tTerm2, ij, 0);
  p[3] = texelFetch(tTerm3, ij, 0);
#if TERM == 9
  p[4] = texelFetch(tTerm4, ij, 0);
  p[5] = texelFetch(tTerm5, ij, 0);
  p[6] = texelFetch(tTerm6, ij, 0);
#endif
  vec3 d = termDirection();
  float t = clamp(d.z, 0.0, 1.0), s = sqrt(max(t - t * t, 0.0)), r = length(d.xy);
  float c1 = r > 0.0 ? d.x / r : 1.0, s1 = r > 0.0 ? d.y / r : 0.0;
  float c2 = c1 * c1 - s1 * s1, s2 = 2.0 * s1 * c1;
  float H[9];
  H[0] = 1.0 / sqrt(2.0 * PI);
  H[1] = sqrt(6.0 / PI) * c1 * s;
  H[2] = sqrt(3.0 / (2.0 * PI)) * (2.0 * t - 1.0);
  H[3] = sqrt(6.0 / PI) * s1 * s;
  H[4] = sqrt(30.0 / PI) * c2 * (t * t - t);
  H[5] = sqrt(30.0 / PI) * c1 * (2.0 * t - 1.0) * s;
  H[6] = sqrt(5.0 / (2.0 * PI)) * (6.0 * t * t - 6.0 * t + 1.0);
  H[7] = sqrt(30.0 / PI) * s1 * (2.0 * t - 1.0) * s;
  H[8] = sqrt(30.0 / PI) * s2 * (t * t - t);
  vec3 sum = vec3(0.0);
  for (int j = 0; j < TERM; j++) {
    int k = 1 + 3 * j; // planes k, k + 1, k + 2: function j's r, g, b (plane 0: the weight)
    sum += H[j] * vec3(p[k / 4][k % 4], p[(k + 1) / 4][(k + 1) % 4], p[(k + 2) / 4][(k + 2) % 4]);
  }
  return decode(p[0].x * encode(value) + sum);
}
#endif

void main() {
  ivec2 ij = ivec2(floor(vTex));
  if (ij.x >= uValid.x || ij.y >= uValid.y) discard;
  vec3 colour;
  float falloff = lightAt(ij); // the value at unit irradiance (the term's too) times the irradiance here
  vec3 value = vec3(0.0), bounce = vec3(0.0); // the relit layers' value at unit light, and the indirect light
  if (uLayer == 0 || uLayer == 10) value = relit(ij);
#if SHADOWS
  if ((uLayer == 0 || uLayer == 10) && uShadows != 0) {
    value *= seen(ij);
    bounce = texelFetch(tShadow, ivec3(ij, SHADOWS / 4), 0).x * texelFetch(tKd, ij, 0).rgb / PI * flatCosine();
  }
#endif
#if TERM
  if (uLayer == 0) colour = srgb((withTerm(ij, value) + bounce) * falloff * uExposure);
#else
  if (uLayer == 0) colour = srgb((value + bounce) * falloff * uExposure);
#endif
  else if (uLayer == 10) colour = srgb((value + bounce) * falloff * uExposure);
  else if (uLayer == 1) colour = texelFetch(tGeo, ij, 0).xyz * 0.5 + 0.5;
  else if (uLayer == 2) colour = srgb(texelFetch(tKd, ij, 0).rgb);
  else if (uLayer == 3) colour = srgb(texelFetch(tKs, ij, 0).rgb * uGain);
  else if (uLayer == 4) colour = texelFetch(tRough, ij, 0).xyz * uGain;
  else if (uLayer == 5) {
    int m = int(texelFetch(tKs, ij, 0).a + 0.5);
    colour = m >= 0 && m < uModels ? uModelColours[m] : vec3(0.0);
  } else if (uLayer == 6) {
    float q = clamp(texelFetch(tKd, ij, 0).a, 0.0, 1.0);
    colour = mix(vec3(0.27, 0.0, 0.33), vec3(0.99, 0.91, 0.14), q);
  } else if (uLayer == 7) {
    int f = int(texelFetch(tKs2, ij, 0).a + 0.5);
    colour = (f & uUntrusted) != 0 ? vec3(0.9, 0.1, 0.1) : (f != 0 ? vec3(0.9, 0.7, 0.1) : vec3(0.15));
  } else if (uLayer == 8) colour = vec3(clamp(texelFetch(tStd, ij, 0)[uStd] * uGain, 0.0, 1.0));
  else colour = srgb(texelFetch(tPhoto, ij, 0).rgb * uPhotoScale * uExposure); // the JPEG's sRGB codes, decoded
  outColour = vec4(colour, 1.0);
}`;

function halfToFloat(h) {
  const e = (h >> 10) & 31, f = h & 1023, s = h >> 15 ? -1 : 1;
  if (e === 0) return s * f * 2 ** -24;
  if (e === 31) return f ? NaN : s * Infinity;
  return s * (1 + f / 1024) * 2 ** (e - 15);
}

// The scale of a photograph's JPEG tile: the number after "torchspec scale=" in its comment (a COM
// segment, 0xFFFE, before the scan).
function photoScale(bytes) {
  for (let i = 2; i + 4 <= bytes.length && bytes[i] === 0xff && bytes[i + 1] !== 0xda; ) {
    const length = (bytes[i + 2] << 8) | bytes[i + 3];
    if (bytes[i + 1] === 0xfe) {
      const found = /torchspec scale=([0-9.eE+-]+)/.exec(new TextDecoder("latin1").decode(bytes.subarray(i + 4, i + 2 + length)));
      if (found) return Number(found[1]);
    }
    i += 2 + length;
  }
  throw new Error("a photograph's tile without its scale (torchspec scale= in the JPEG's comment)");
}

function colourOf(hex) {
  const v = parseInt(hex.slice(1), 16);
  return [(v >> 16) / 255, ((v >> 8) & 255) / 255, (v & 255) / 255];
}

class Viewer {
  constructor(manifest) {
    this.m = manifest;
    this.canvas = document.getElementById("view");
    const gl = this.canvas.getContext("webgl2", { antialias: false, alpha: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    this.programs = [this.compile(false)]; // the point light's, and an extended light's
    if ((manifest.kernel_nodes || []).length) this.programs.push(this.compile(true));
    this.use(false);
    this.tiles = new Map(); // key -> {state, textures, used}
    this.queue = new Set();
    this.fetching = 0;
    this.frames = 0;
    this.drawMs = 0;
    this.light = [0, 0, 1]; // the light's direction (a near light's from the image's centre)
    this.distance = manifest.near_radius ?? Infinity; // a light's distance in image widths (Infinity: distant)
    this.position = null; // a near light's position (image widths from the image's centre), or null: distant
    this.own = false; // the position is the snapped frame's own (the capture's, or the fit's calibrated)
    this.perPixel = false; // a near light's direction at each pixel (else at each of render's blocks)
    this.frame = -1; // the captured frame nearest the light
    this.layer = 0;
    this.exposure = 1;
    this.std = 0;
    this.shadows = Boolean(manifest.shadows); // cast shadows (maps with a height)
    this.compare = manifest.lights.length > 0;
    this.snap = manifest.lights.length > 0;
    this.nodes = manifest.kernel_nodes || [];
    this.extended = this.nodes.length > 0; // the capture's kernel (else a point light)
    this.complete = false;
    this.readouts = 0; // clicks read (canvasEvents)
    this.readout = Promise.resolve([]);
    this.lastInput = -Infinity;
    this.scale = 1;
    this.fit();
  }

  // The shader program of a point light or (extended) the capture's kernel: {p, u} (uniforms by name).
  compile(extended) {
    const gl = this.gl;
    const shader = (type, source) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, source);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      return s;
    };
    const p = gl.createProgram();
    gl.attachShader(p, shader(gl.VERTEX_SHADER, VERTEX));
    const curve = this.m.term_encoding && this.m.term_encoding.transfer === "response" ? this.m.term_encoding : null;
    const shadows = this.m.shadows ? this.m.shadows.azimuths : 0;
    const defines = `\n#define EXTENDED ${extended ? 1 : 0}\n#define TERM ${this.m.term || 0}\n#define CURVE ${curve ? 1 : 0}\n#define SHADOWS ${shadows}\n`;
    const source = FRAGMENT.replace("\n", defines); // after #version
    gl.attachShader(p, shader(gl.FRAGMENT_SHADER, source));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
    gl.useProgram(p);
    const u = (this.u = {});
    for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); i++) {
      const name = gl.getActiveUniform(p, i).name.replace("[0]", "");
      u[name] = gl.getUniformLocation(p, name);
    }
    ["tGeo", "tRough", "tKd", "tKs", "tKs2", "tStd", "tPhoto"].forEach((n, i) => gl.uniform1i(this.u[n], i));
    for (let i = 0; i < 7; i++) if (this.u[`tTerm${i}`]) gl.uniform1i(this.u[`tTerm${i}`], TILE_UNITS + 1 + i);
    if (curve) ["gamma", "offset", "contrast", "slope"].forEach((n) => gl.uniform3fv(this.u[`u${n[0].toUpperCase()}${n.slice(1)}`], curve[n]));
    if (shadows) {
      const sh = this.m.shadows;
      gl.uniform1i(this.u.tShadow, SHADOW_UNIT);
      gl.uniform1f(this.u.uSoftness, (sh.softness_deg * Math.PI) / 180);
      // the point light's program (the kernel unticked, or none): the penumbra alone
      gl.uniformMatrix2fv(this.u.uKernelCov, false, extended ? sh.covariance.flat() : [0, 0, 0, 0]);
      gl.uniform2fv(this.u.uKernelOffset, sh.offset);
      gl.uniform1i(this.u.uKernelAngular, sh.angular ? 1 : 0);
    }
    gl.uniform1f(this.u.uTile, this.m.tile);
    const colours = (this.m.model_colours || []).slice(0, 8);
    gl.uniform1i(this.u.uModels, colours.length);
    if (colours.length) gl.uniform3fv(this.u.uModelColours, colours.flatMap(colourOf));
    let untrusted = 0;
    for (const name of this.m.untrusted_flags) untrusted |= this.m.flag_bits[name] || 0;
    gl.uniform1i(this.u.uUntrusted, untrusted);
    gl.uniform3fv(this.u.uView, this.m.view);
    gl.uniform2i(this.u.uSize, this.m.width, this.m.height);
    const nodes = this.m.kernel_nodes || [];
    if (nodes.length) gl.uniform3fv(this.u.uNode, nodes.flat());
    gl.uniform1i(this.u.uAngular, this.m.kernel_angular ? 1 : 0);
    gl.uniform1f(this.u.uSigma, this.m.kernel_sigma || 0);
    const rule = this.m.kernel_lobe_rule || [];
    gl.uniform1i(this.u.uLobeNodes, rule.length);
    if (rule.length) gl.uniform3fv(this.u.uLobeRule, rule.flat());
    const table = this.m.kernel_diffuse || [];
    gl.uniform1i(this.u.uDiffuseRows, table.length);
    gl.uniform1f(this.u.uDiffuseReach, this.m.kernel_diffuse_reach || 1);
    if (table.length) gl.uniform4fv(this.u.uDiffuse, table.flat());
    gl.uniform1i(this.u.uNodes, nodes.length);
    return { p, u };
  }

  use(extended) {
    const program = this.programs[extended && this.programs.length > 1 ? 1 : 0];
    if (this.current !== program) this.gl.useProgram(program.p);
    this.current = program;
    this.u = program.u;
  }

  // The view: zoom (screen pixels per level-0 pixel) and the image point at the centre of a panel.
  panels() {
    const w = this.canvas.width, h = this.canvas.height;
    if (this.compare && this.frame >= 0) {
      const half = Math.floor(w / 2);
      return [{ x: 0, w: half, h, photo: false }, { x: half, w: w - half, h, photo: true }];
    }
    return [{ x: 0, w, h, photo: false }];
  }

  fit() {
    this.resize();
    const p = this.panels()[0];
    this.zoom = Math.min(p.w / this.m.width, p.h / this.m.height);
    this.centre = [this.m.width / 2, this.m.height / 2];
    this.request();
  }

  resize() {
    const r = this.canvas.getBoundingClientRect();
    const w = Math.max(1, Math.round(r.width * devicePixelRatio)), h = Math.max(1, Math.round(r.height * devicePixelRatio));
    if (this.canvas.width !== w || this.canvas.height !== h) [this.canvas.width, this.canvas.height] = [w, h];
  }

  level() {
    const top = this.m.levels.length - 1;
    return Math.max(0, Math.min(top, Math.floor(Math.log2(1 / this.zoom) + 1e-9)));
  }

  // Tiles of `level` that a panel shows: [row, column] pairs.
  visible(level, p) {
    const span = this.m.tile * 2 ** level, [rows, cols] = this.grid(level);
    const x0 = this.centre[0] - p.w / 2 / this.zoom, x1 = this.centre[0] + p.w / 2 / this.zoom;
    const y0 = this.centre[1] - p.h / 2 / this.zoom, y1 = this.centre[1] + p.h / 2 / this.zoom;
    const out = [];
    for (let r = Math.max(0, Math.floor(y0 / span)); r < Math.min(rows, Math.ceil(y1 / span)); r++)
      for (let c = Math.max(0, Math.floor(x0 / span)); c < Math.min(cols, Math.ceil(x1 / span)); c++) out.push([r, c]);
    return out;
  }

  grid(level) {
    const [h, w] = this.m.levels[level];
    return [Math.ceil(h / this.m.tile), Math.ceil(w / this.m.tile)];
  }

  url(photo, level, r, c) {
    return photo ? `photo/${this.frame}/${level}/${r}_${c}.jpg` : `tiles/${level}/${r}_${c}.bin`;
  }

  // The tile at `url`, uploaded; null while it loads (its fetch queued) or waits to be asked again.
  tile(url) {
    const t = this.tiles.get(url);
    if (t && !(t.state === "later" && performance.now() >= t.retry)) {
      t.used = performance.now();
      return t.state === "ready" ? t : null;
    }
    this.queue.add(url);
    this.pump();
    return null;
  }

  pump() {
    while (this.fetching < MAX_FETCHES && this.queue.size) {
      const url = this.queue.values().next().value;
      this.queue.delete(url);
      const entry = { state: "loading", used: performance.now(), textures: [] };
      this.tiles.set(url, entry);
      this.fetching++;
      fetch(url)
        .then((r) => {
          if (r.status === 503) return null; // not made yet: the connection is freed for others
          return r.ok ? r.arrayBuffer() : Promise.reject(new Error(`${url}: ${r.status}`));
        })
        .then((buffer) => {
          if (buffer && url.startsWith("photo")) return this.uploadPhoto(entry, buffer);
          if (buffer) return this.upload(entry, buffer);
          [entry.state, entry.retry] = ["later", performance.now() + RETRY_MS];
          setTimeout(() => this.request(), RETRY_MS);
        })
        .catch((e) => {
          entry.state = "error";
          this.status(String(e));
        })
        .finally(() => {
          this.fetching--;
          this.pump();
          this.arrived();
        });
    }
  }

  // A map tile's textures, in file order; the cast shadows' (float16, named shadow*) as one
  // texture array (entry.shadow): a sampler unit for all of them.
  upload(entry, buffer) {
    const gl = this.gl, n = this.m.tile;
    const layers = this.m.textures.filter((spec) => spec.name.startsWith("shadow")).length;
    let offset = 0;
    for (const spec of this.m.textures) {
      const f32 = spec.dtype === "float32";
      const data = f32 ? new Float32Array(buffer, offset, n * n * 4) : new Uint16Array(buffer, offset, n * n * 4);
      offset += n * n * 4 * (f32 ? 4 : 2);
      if (spec.name.startsWith("shadow")) {
        if (!entry.shadow) {
          entry.shadow = gl.createTexture();
          gl.bindTexture(gl.TEXTURE_2D_ARRAY, entry.shadow);
          gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
          gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
          gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGBA16F, n, n, layers);
          entry.layer = 0;
        }
        gl.bindTexture(gl.TEXTURE_2D_ARRAY, entry.shadow);
        gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
        gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, entry.layer++, n, n, 1, gl.RGBA, gl.HALF_FLOAT, data);
        continue;
      }
      const tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
      gl.texImage2D(gl.TEXTURE_2D, 0, f32 ? gl.RGBA32F : gl.RGBA16F, n, n, 0, gl.RGBA, f32 ? gl.FLOAT : gl.HALF_FLOAT, data);
      entry.textures.push(tex);
    }
    entry.state = "ready";
    this.evict();
  }

  // A photograph's tile: a JPEG of the tile's own size (torchspec/view/tiles.py photo_jpeg), its
  // codes sRGB (decoded by the texture: SRGB8_ALPHA8), times the scale its comment holds.
  async uploadPhoto(entry, buffer) {
    const bitmap = await createImageBitmap(new Blob([buffer], { type: "image/jpeg" }),
                                           { colorSpaceConversion: "none", premultiplyAlpha: "none" });
    const gl = this.gl, tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.SRGB8_ALPHA8, gl.RGBA, gl.UNSIGNED_BYTE, bitmap);
    bitmap.close();
    entry.textures.push(tex);
    entry.scale = photoScale(new Uint8Array(buffer));
    entry.state = "ready";
    this.evict();
  }

  evict() {
    if (this.tiles.size <= MAX_TILES) return;
    const ready = [...this.tiles.entries()].filter(([, t]) => t.state === "ready").sort((a, b) => a[1].used - b[1].used);
    for (const [url, t] of ready.slice(0, this.tiles.size - MAX_TILES)) {
      t.textures.forEach((x) => this.gl.deleteTexture(x));
      if (t.shadow) this.gl.deleteTexture(t.shadow);
      this.tiles.delete(url);
    }
  }

  // A tile arrived: draw when the last one is in, or every TILE_FRAME_MS while more come (each
  // frame of a big canvas takes long without a GPU).
  arrived() {
    if (!this.drawn || (this.fetching === 0 && this.queue.size === 0)) return this.request();
    if (!this.soon) this.soon = setTimeout(() => ((this.soon = 0), this.request()), TILE_FRAME_MS);
  }

  request() {
    if (!this.pending) this.pending = requestAnimationFrame(() => this.draw());
  }

  // One frame. While the user drags or zooms (the last input under INTERACTIVE_MS ago), it is
  // drawn at a reduced scale chosen to keep a frame near FRAME_MS, and scaled up; the full
  // resolution follows when the input stops. Each panel draws the top level under the tiles of
  // the level that matches the zoom only where one of those is still loading.
  draw() {
    this.pending = 0;
    const start = performance.now(), gl = this.gl;
    this.resize();
    const interactive = start - this.lastInput < INTERACTIVE_MS;
    const scale = interactive ? this.scale : 1;
    const width = this.canvas.width, height = this.canvas.height;
    const w = Math.max(1, Math.round(width * scale)), h = Math.max(1, Math.round(height * scale));
    gl.bindFramebuffer(gl.FRAMEBUFFER, scale < 1 ? this.target(w, h) : null);
    gl.viewport(0, 0, w, h);
    gl.clearColor(0.125, 0.125, 0.125, 1);
    gl.clear(gl.COLOR_BUFFER_BIT);
    this.use(this.extended);
    gl.uniform3fv(this.u.uLight, this.light);
    gl.uniform4fv(this.u.uNear, this.position ? [...this.position, 1] : [0, 0, 0, 0]);
    gl.uniform1i(this.u.uBlock, this.block() || 1);
    gl.uniform1f(this.u.uExposure, this.exposure);
    gl.uniform1i(this.u.uStd, this.std);
    if (this.u.uShadows) gl.uniform1i(this.u.uShadows, this.shadows ? 1 : 0);
    const target = this.level(), top = this.m.levels.length - 1;
    let complete = true;
    this.queue.clear(); // only what this frame wants is fetched
    for (const p of this.panels()) {
      gl.viewport(Math.round(p.x * scale), 0, Math.round((p.x + p.w) * scale) - Math.round(p.x * scale), h);
      this.setLayer(p.photo ? PHOTO_LAYER : this.layer);
      const at = (level) => this.visible(level, p).map(([r, c]) => [r, c, this.tile(this.url(p.photo, level, r, c))]);
      const under = target === top ? [] : at(top); // asked for first: it shows first
      const tiles = at(target);
      if (tiles.some(([, , t]) => !t)) for (const [r, c, t] of under) if (t) this.drawTile(t, top, r, c, p);
      for (const [r, c, t] of tiles) {
        if (t) this.drawTile(t, target, r, c, p);
        else complete = false;
      }
    }
    if (scale < 1) {
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.fbo);
      gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
      gl.blitFramebuffer(0, 0, w, h, 0, 0, width, height, gl.COLOR_BUFFER_BIT, gl.LINEAR);
    }
    if (interactive) {
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4)); // wait for the frame: its real time
      const ms = performance.now() - start;
      if (ms > FRAME_MS * 1.5 && this.scale > 1 / 8) this.scale /= Math.SQRT2;
      else if (ms < FRAME_MS / 2.5 && this.scale < 1) this.scale = Math.min(1, this.scale * Math.SQRT2);
      clearTimeout(this.idle);
      this.idle = setTimeout(() => this.request(), INTERACTIVE_MS);
    }
    if (this.firstImage === undefined && this.drawn) {
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));
      this.firstImage = performance.now(); // ms since the page's navigation: when it first showed the maps
    }
    this.complete = complete && scale === 1;
    this.frames++;
    this.drawMs = performance.now() - start;
  }

  target(w, h) {
    const gl = this.gl;
    if (!this.fbo || this.fboSize[0] !== w || this.fboSize[1] !== h) {
      if (this.fbo) [gl.deleteFramebuffer(this.fbo), gl.deleteTexture(this.fboTexture)];
      this.fboTexture = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, this.fboTexture);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, w, h);
      this.fbo = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.fboTexture, 0);
      this.fboSize = [w, h];
    }
    return this.fbo;
  }

  setLayer(layer) {
    const gl = this.gl, ranges = this.m.ranges;
    gl.uniform1i(this.u.uLayer, layer);
    const stds = ["std_normal_deg", "std_diffuse", "std_specular", "std_roughness"];
    const gain = { 3: 1 / ranges.specular, 4: 1 / ranges.alpha, 8: 1 / (ranges[stds[this.std]] || 1) }[layer] || 1;
    gl.uniform1f(this.u.uGain, gain);
  }

  drawTile(t, level, r, c, p) {
    const gl = this.gl, n = this.m.tile, span = n * 2 ** level;
    this.drawn = true;
    const [h, w] = this.m.levels[level];
    t.textures.forEach((x, i) => {
      gl.activeTexture(gl.TEXTURE0 + (t.textures.length === 1 ? TILE_UNITS : i < TILE_UNITS ? i : i + 1));
      gl.bindTexture(gl.TEXTURE_2D, x);
    });
    if (t.shadow) {
      gl.activeTexture(gl.TEXTURE0 + SHADOW_UNIT);
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, t.shadow);
    }
    gl.uniform2i(this.u.uValid, Math.min(n, w - c * n), Math.min(n, h - r * n));
    if (t.scale !== undefined) gl.uniform1f(this.u.uPhotoScale, t.scale);
    gl.uniform3f(this.u.uPlace, c * span, r * span, 2 ** level);
    const sx = (x) => ((x - this.centre[0]) * this.zoom + p.w / 2) / p.w * 2 - 1;
    const sy = (y) => 1 - ((y - this.centre[1]) * this.zoom + p.h / 2) / p.h * 2;
    gl.uniform4f(this.u.uRect, sx(c * span), sy(r * span), sx((c + 1) * span), sy((r + 1) * span));
    gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
  }

  // The light from a direction, snapped to the nearest captured light when asked.
  setLight(l) {
    let [x, y] = l, r = Math.hypot(x, y);
    if (r > 0.995) [x, y, r] = [(x * 0.995) / r, (y * 0.995) / r, 0.995];
    let light = [x, y, Math.sqrt(Math.max(0, 1 - r * r))];
    let best = -1, k = -1;
    this.m.lights.forEach((d, i) => {
      const c = d[0] * light[0] + d[1] * light[1] + d[2] * light[2];
      if (c > best) [best, k] = [c, i];
    });
    this.frame = k;
    const snapped = this.snap && k >= 0;
    this.light = snapped ? this.m.lights[k].slice() : light;
    this.position = this.place(snapped ? k : -1);
    this.own = Boolean(this.position && snapped && (this.m.positions || [])[k]);
    if (this.position) this.light = this.position.map((x) => x / Math.hypot(...this.position));
    this.onLight();
    this.request();
  }

  // A near light's position at this.distance along this.light, or captured frame k's own position
  // (the capture's, or the fit's calibrated: manifest positions); null for a distant light.
  place(k) {
    if (!Number.isFinite(this.distance)) return null;
    const own = k >= 0 ? (this.m.positions || [])[k] : null;
    return own ? own.slice() : this.light.map((x) => x * this.distance);
  }

  // The side (pixels) of the blocks whose centre a near light's direction and falloff are taken at:
  // 1 at each pixel (asked), else torchspec render's (renderBlock); null for a distant light.
  block() {
    return this.position ? (this.perPixel ? 1 : this.renderBlock()) : null;
  }

  // torchspec render's block for the near light at this.position: a frame's own position, the
  // block render_capture lights every frame with (manifest near_block, of all the capture's
  // positions); a light of the page's own (or a frame's direction at the chosen distance), render_near's
  // for that one light (torchspec.pipeline.tiling.near_block): 2 tan(block_angle) times its least
  // distance from the image (|x| <= 1/2, |y| <= H / 2W, z = 0, image widths) in pixels, floored,
  // within least_block .. most_block.
  renderBlock() {
    const m = this.m;
    if (this.own && m.near_block != null) return m.near_block;
    const [x, y, z] = this.position;
    const dx = Math.max(Math.abs(x) - 0.5, 0), dy = Math.max(Math.abs(y) - (0.5 * m.height) / m.width, 0);
    const across = Math.floor(2 * Math.tan(m.block_angle) * Math.sqrt(dx * dx + dy * dy + z * z) * m.width);
    return Math.max(m.least_block, Math.min(m.most_block, across));
  }

  // Image point (level-0 pixel coordinates) under a canvas point (CSS pixels).
  imagePoint(cx, cy) {
    const x = cx * devicePixelRatio, y = cy * devicePixelRatio;
    const p = this.panels().find((q) => x >= q.x && x < q.x + q.w) || this.panels()[0];
    return [(x - p.x - p.w / 2) / this.zoom + this.centre[0], (y - p.h / 2) / this.zoom + this.centre[1]];
  }

  async pick(x, y) {
    const px = Math.floor(x), py = Math.floor(y), n = this.m.tile;
    if (px < 0 || py < 0 || px >= this.m.width || py >= this.m.height) return null;
    const buffer = await (await fetch(this.url(false, 0, Math.floor(py / n), Math.floor(px / n)))).arrayBuffer();
    const i = ((py % n) * n + (px % n)) * 4, out = { x: px, y: py };
    let offset = 0;
    for (const spec of this.m.textures) {
      const f32 = spec.dtype === "float32";
      const a = f32 ? new Float32Array(buffer, offset, n * n * 4) : new Uint16Array(buffer, offset, n * n * 4);
      spec.planes.forEach((name, j) => (out[name] = f32 ? a[i + j] : halfToFloat(a[i + j])));
      offset += n * n * 4 * (f32 ? 4 : 2);
    }
    return out;
  }

  status(text) {
    document.getElementById("status").textContent = text;
  }

  onLight() {}
}

function describe(m, v) {
  const f = (x) => (Math.abs(x) >= 1e-3 || x === 0 ? x.toFixed(4) : x.toExponential(2));
  const rows = [["pixel", `${v.x}, ${v.y}`], ["normal", [v.normal_x, v.normal_y, v.normal_z].map(f).join(" ")]];
  rows.push(["k_d", [v.kd_r, v.kd_g, v.kd_b].map(f).join(" ")], ["k_s", [v.ks_r, v.ks_g, v.ks_b].map(f).join(" ")]);
  rows.push(["alpha", `${f(v.alpha_x)} ${f(v.alpha_y)}`], ["rotation", f(v.rotation)]);
  if (v.ks2_r || v.ks2_g || v.ks2_b) rows.push(["k_s2", [v.ks2_r, v.ks2_g, v.ks2_b].map(f).join(" ")], ["alpha2", `${f(v.alpha2_x)} ${f(v.alpha2_y)}`]);
  if (m.layers.includes("model")) rows.push(["model", m.model_codes[Math.round(v.model)] || String(v.model)]);
  if (m.layers.includes("quality")) rows.push(["quality", f(v.quality)]);
  if (m.layers.includes("flags")) {
    const names = Object.entries(m.flag_bits).filter(([, b]) => Math.round(v.flags) & b).map(([n]) => n);
    rows.push(["flags", names.join(", ") || "none"]);
  }
  if (m.term) rows.push(["term w", f(v.term_weight)]);
  if (m.shadows) rows.push(["indirect share", f(v.indirect)]);
  if (m.layers.includes("std")) {
    rows.push(["std normal", `${f(v.std_normal_deg)} deg`], ["std k_d", f(v.std_diffuse)]);
    rows.push(["std k_s", f(v.std_specular)], ["std alpha", f(v.std_roughness)]);
  }
  return rows;
}

function hemisphere(viewer) {
  const hemi = document.getElementById("hemi"), ctx = hemi.getContext("2d");
  const R = hemi.width / 2 - 6, C = hemi.width / 2;
  const drawHemi = () => {
    ctx.clearRect(0, 0, hemi.width, hemi.height);
    ctx.strokeStyle = "#777";
    for (const e of [0, 30, 60]) {
      ctx.beginPath();
      ctx.arc(C, C, R * Math.cos((e * Math.PI) / 180), 0, 2 * Math.PI);
      ctx.stroke();
    }
    ctx.fillStyle = "#5af";
    viewer.m.lights.forEach((d, i) => {
      ctx.fillStyle = i === viewer.frame ? "#fff" : "#5af";
      ctx.fillRect(C + d[0] * R - 2, C - d[1] * R - 2, 4, 4);
    });
    ctx.fillStyle = "#fc3";
    ctx.beginPath();
    ctx.arc(C + viewer.light[0] * R, C - viewer.light[1] * R, 5, 0, 2 * Math.PI);
    ctx.fill();
    const [x, y, z] = viewer.light, el = (Math.asin(Math.min(1, z)) * 180) / Math.PI;
    const frame = viewer.frame >= 0 ? `, frame ${viewer.frame}` : "";
    document.getElementById("light").textContent = `light ${x.toFixed(3)} ${y.toFixed(3)} ${z.toFixed(3)} (elevation ${el.toFixed(1)} deg${frame})`;
    document.getElementById("kernel").textContent = viewer.extended ? viewer.m.kernel_label : "point light";
    document.getElementById("near").textContent = nearText(viewer);
    document.getElementById("pixel-label").hidden = !viewer.position;
    document.getElementById("distance-value").textContent = Number.isFinite(viewer.distance) ? `${viewer.distance.toPrecision(3)} widths` : "infinite";
  };
  const move = (e) => {
    viewer.lastInput = performance.now();
    viewer.setLight([(e.offsetX - C) / R, -(e.offsetY - C) / R]);
  };
  hemi.addEventListener("pointerdown", (e) => {
    hemi.setPointerCapture(e.pointerId);
    move(e);
  });
  hemi.addEventListener("pointermove", (e) => e.buttons && move(e));
  viewer.onLight = drawHemi;
  drawHemi();
}

// What the page says of the light's distance: a distant light, or a near one: how far, from where
// its position comes, and where its direction is taken.
function nearText(v) {
  if (!v.position) return "distant light: one direction for every pixel";
  const m = v.m, block = v.block();
  const from = v.own ? `frame ${v.frame}'s position (${m.near_source})` : "along the light's direction";
  const whose = v.own && m.near_block != null ? "the capture's lights" : "this light";
  const where = v.perPixel ? "at each pixel" : `at the centre of each block of ${block} x ${block} pixels, as torchspec render takes it for ${whose}`;
  return `near light ${Math.hypot(...v.position).toFixed(3)} widths away, ${from}; its direction and falloff ${where}`;
}

// The distance slider's steps: 0.25 image widths times 2^(step / 10); its last step, infinite.
const FAR_STEP = 80;
const distanceOf = (step) => (step >= FAR_STEP ? Infinity : 0.25 * 2 ** (step / 10));
const stepOf = (distance) => (Number.isFinite(distance) ? Math.max(0, Math.min(FAR_STEP - 1, Math.round(10 * Math.log2(distance / 0.25)))) : FAR_STEP);

// What the relit layers show: the fit's model with its residual term, or the physical maps alone.
function showing(viewer) {
  const name = LAYERS[viewer.layer], term = viewer.m.term > 0;
  let text = "";
  if (name === "relit") text = term ? "relit: model + residual term" : "relit: the physical maps (the fit has no residual term)";
  if (name === "physical") text = "relit: physical maps only (the residual term off), as a renderer uses them";
  if (text && viewer.m.shadows) text += viewer.shadows ? ", with their cast shadows" : ", cast shadows off";
  document.getElementById("shown").textContent = text;
}

function controls(viewer) {
  const m = viewer.m, bar = document.getElementById("layers");
  for (const name of m.layers) {
    const b = document.createElement("button");
    b.textContent = name;
    b.onclick = () => {
      viewer.layer = LAYERS.indexOf(name);
      [...bar.children].forEach((x) => x.classList.toggle("on", x === b));
      showing(viewer);
      viewer.request();
    };
    bar.appendChild(b);
  }
  bar.firstChild.classList.add("on");
  showing(viewer);
  const exposure = document.getElementById("exposure");
  exposure.oninput = () => {
    viewer.exposure = 2 ** Number(exposure.value);
    document.getElementById("exposure-value").textContent = viewer.exposure.toPrecision(3);
    viewer.request();
  };
  const distance = document.getElementById("distance");
  distance.value = stepOf(viewer.distance);
  distance.oninput = () => ((viewer.distance = distanceOf(Number(distance.value))), viewer.setLight(viewer.light));
  document.getElementById("pixel").onchange = (e) => ((viewer.perPixel = e.target.checked), viewer.onLight(), viewer.request());
  document.getElementById("std").onchange = (e) => ((viewer.std = Number(e.target.value)), viewer.request());
  document.getElementById("shadows-label").hidden = !m.shadows;
  document.getElementById("shadows").onchange = (e) => ((viewer.shadows = e.target.checked), showing(viewer), viewer.request());
  document.getElementById("fit").onclick = () => viewer.fit();
  document.getElementById("one").onclick = () => ((viewer.zoom = 1 / devicePixelRatio), viewer.request());
  for (const id of ["snap", "compare", "extended"]) {
    document.getElementById(`${id}-label`).hidden = id === "extended" ? !viewer.nodes.length : m.lights.length === 0;
    document.getElementById(id).onchange = (e) => ((viewer[id] = e.target.checked), viewer.setLight(viewer.light));
  }
  document.getElementById("title").textContent = `torchspec: ${m.title} (${m.width} x ${m.height})`;
}

function canvasEvents(viewer) {
  const canvas = viewer.canvas, drag = document.getElementById("drag");
  let down = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    down = { x: e.offsetX, y: e.offsetY, moved: false, centre: viewer.centre.slice() };
    down.pan = e.shiftKey || e.button !== 0 || drag.value === "pan";
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!down) return;
    const dx = e.offsetX - down.x, dy = e.offsetY - down.y;
    down.moved = down.moved || Math.hypot(dx, dy) > 3;
    if (!down.moved) return;
    viewer.lastInput = performance.now();
    if (down.pan) {
      const s = devicePixelRatio / viewer.zoom;
      viewer.centre = [down.centre[0] - dx * s, down.centre[1] - dy * s];
      viewer.request();
    } else {
      const r = canvas.getBoundingClientRect(), p = viewer.panels(), w = p[0].w / devicePixelRatio;
      const x = e.offsetX % w, size = Math.min(w, r.height) / 2;
      viewer.setLight([(x - w / 2) / size, -(e.offsetY - r.height / 2) / size]);
    }
  });
  // A click reads its pixel (a tile fetched): viewer.readouts counts the readouts begun and
  // viewer.readout is the promise of the last one's rows, once they are in the table.
  canvas.addEventListener("pointerup", (e) => {
    const click = down && !down.moved;
    down = null;
    if (!click) return;
    const [x, y] = viewer.imagePoint(e.offsetX, e.offsetY), seq = ++viewer.readouts;
    viewer.readout = viewer.pick(x, y).then((v) => {
      const table = document.getElementById("info"), rows = v ? describe(viewer.m, v) : [];
      if (seq !== viewer.readouts) return rows; // a later click's readout owns the table
      table.innerHTML = "";
      for (const [k, val] of rows) table.insertRow().append(...[k, val].map((t) => Object.assign(document.createElement("td"), { textContent: t })));
      return rows;
    });
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    const [x, y] = viewer.imagePoint(e.offsetX, e.offsetY), f = Math.exp(-e.deltaY * 0.002);
    viewer.lastInput = performance.now();
    viewer.zoom *= f;
    viewer.centre = [x - (x - viewer.centre[0]) / f, y - (y - viewer.centre[1]) / f];
    viewer.request();
  }, { passive: false });
  new ResizeObserver(() => viewer.request()).observe(canvas);
}

// For tests and scripts (torchspec/view/browser.py): the viewer, a promise of its settling (every
// tile the view wants drawn), and the canvas's pixels read back (RGBA, rows top to bottom, base64).
window.torchspecView = {
  ready: fetch("manifest.json")
    .then((r) => r.json())
    .then((m) => {
      const viewer = new Viewer(m);
      controls(viewer);
      hemisphere(viewer);
      canvasEvents(viewer);
      if (m.lights.length) viewer.setLight([0, 0, 1]);
      viewer.fit(); // to the layout the controls leave (their labels may wrap the bar) and the photograph's panel
      window.torchspecView.viewer = viewer;
      return viewer;
    })
    .catch((e) => {
      document.getElementById("status").textContent = `cannot show the maps: ${e.message}`;
      throw e;
    }),
  // Set the view: {light: [x, y(, z)], distance (image widths; null: infinite), pixel, layer, exposure,
  // snap, compare, extended, shadows, zoom, centre, origin} (origin: 1:1, the image's top-left pixel at the
  // canvas's; pixel: a near light's direction at each pixel); returns the state it shows (block: the
  // side in pixels of the blocks a near light's direction is taken at, 1 at each pixel, null: distant).
  show(o) {
    const v = this.viewer;
    for (const key of ["exposure", "snap", "compare", "extended", "zoom", "centre", "std", "shadows"]) if (key in o) v[key] = o[key];
    v.extended = v.extended && v.nodes.length > 0;
    v.shadows = v.shadows && Boolean(v.m.shadows);
    document.getElementById("shadows").checked = v.shadows;
    showing(v);
    if ("layer" in o) {
      v.layer = LAYERS.indexOf(o.layer);
      [...document.getElementById("layers").children].forEach((b) => b.classList.toggle("on", b.textContent === o.layer));
      showing(v);
    }
    if ("distance" in o) v.distance = o.distance ?? Infinity; // JSON has no Infinity: null
    if ("pixel" in o) v.perPixel = o.pixel;
    for (const id of ["snap", "compare", "extended"]) document.getElementById(id).checked = v[id];
    document.getElementById("pixel").checked = v.perPixel;
    document.getElementById("distance").value = stepOf(v.distance);
    if (o.light || "distance" in o || "snap" in o) v.setLight(o.light || v.light);
    v.onLight(); // the light's text as set: the layout it leaves
    v.resize(); // the canvas's size in that layout, not at the last frame's: an origin or panel is placed in it
    if (o.origin) {
      v.zoom = 1;
      v.centre = [v.panels()[0].w / 2, v.canvas.height / 2];
    }
    v.request();
    return { width: v.canvas.width, height: v.canvas.height, panels: v.panels(), frame: v.frame, light: v.light, extended: v.extended,
             position: v.position, distance: Number.isFinite(v.distance) ? v.distance : null, block: v.block() };
  },
  // Frames per second of `count` relit frames, the light circling at `zenith` radians: each
  // frame drawn and finished (one pixel read back) before the next.
  bench(count, zenith) {
    const v = this.viewer, gl = v.gl, one = new Uint8Array(4), start = performance.now();
    for (let i = 0; i < count; i++) {
      const phi = (2 * Math.PI * i) / count;
      v.setLight([Math.sin(zenith) * Math.cos(phi), Math.sin(zenith) * Math.sin(phi)]);
      cancelAnimationFrame(v.pending);
      v.draw();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, one);
    }
    return (count * 1000) / (performance.now() - start);
  },
  // The rows of the `count`-th click's readout (counted from the page's load), once they are in
  // the table: waits for the click to arrive, then for its pixel's tile.
  readout(count) {
    const v = this.viewer;
    return new Promise((resolve) => {
      const check = () => (v.readouts >= count ? resolve(v.readout) : setTimeout(check, 5));
      check();
    });
  },
  settle() {
    const v = this.viewer;
    return new Promise((resolve) => {
      const check = () => {
        if (v.complete && !v.pending && v.fetching === 0) resolve(v.frames);
        else setTimeout(check, 5); // a tile's arrival asks for a frame
      };
      v.request();
      setTimeout(check, 0);
    });
  },
  read(x, y, w, h) {
    const gl = this.viewer.gl, out = new Uint8Array(w * h * 4);
    gl.readPixels(x, gl.drawingBufferHeight - y - h, w, h, gl.RGBA, gl.UNSIGNED_BYTE, out);
    const flipped = new Uint8Array(w * h * 4);
    for (let r = 0; r < h; r++) flipped.set(out.subarray((h - 1 - r) * w * 4, (h - r) * w * 4), r * w * 4);
    let s = "";
    for (let i = 0; i < flipped.length; i += 32768) s += String.fromCharCode(...flipped.subarray(i, i + 32768));
    return btoa(s);
  },
};
