/* Direct light of one lamp, E(p) = sum over its virtual points of E_point(p) V(p, l).
 *
 * The numpy twin is core.lighting.lamp_irradiance with core.lights.light_contributions;
 * each step mirrors it in float32 (same formulas, same epsilons, same "above" and "lit"
 * tests) so the two agree to float32 rounding. One invocation per sample; samples are
 * laid out row-major in a 2D grid (sample_width wide).
 *
 * positions  RGBA32F: sample position xyz, relative to the call's origin
 * normals    RGBA32F: shading normal xyz
 * geometric  RGBA32F: geometric normal xyz
 * lamps      RGBA32F, 4 texels per virtual point (one row each, see direct.py):
 *              0: position xyz relative to the origin (to_light for a sun), w kind
 *              1: rgb irradiance scale (colour times the kind's constant)
 *              2: xyz spot axis or area facing direction, w spot cone offset c0
 *              3: x spot band (0: a hard cone)
 * shadow_data (layers) RGBA32F, per sample:
 *              fractions: layers [0, region_layers) lit, then as many of traced,
 *                4 regions per texel (exact integer counts)
 *              exact: one layer per 64 points, 16 points per channel as an exact
 *                integer bit mask of the points whose shadow ray was blocked
 * regions    RGBA32F, one texel per region: centre c_j xyz
 * accumulated RGBA32F image: this lamp's irradiance rgb, written
 */

#define KIND_SUN 0
#define KIND_POINT 1
#define KIND_SPOT 2
#define KIND_AREA 3
#define SHADOW_FRACTIONS 1
#define SHADOW_EXACT 2
#define MIN_DISTANCE 1e-12 /* core.lights: receivers closer than this get nothing */

/* core.lights.spot_mask. cos(angle) - cos(half) is written as c0 - |f - a|^2 / 2 with
 * c0 = (1 + |a|^2) / 2 - cos(half) from the CPU: for a narrow blend band the direct
 * difference of two cosines near 1 would lose most of float32's digits. */
float spot_mask(vec3 from_light, vec3 axis, float c0, float band)
{
  vec3 d = from_light - axis;
  float above_edge = c0 - 0.5 * dot(d, d);
  if (band <= 0.0) {
    return above_edge > 0.0 ? 1.0 : 0.0;
  }
  float x = clamp(above_edge / band, 0.0, 1.0);
  return x * x * (3.0 - 2.0 * x);
}

/* core.shadows.ShadowFractions.visibility: sum_j a_j lit_j / sum_j a_j traced_j. */
float fractions_visibility(ivec2 cell, vec3 to_light)
{
  float numerator = 0.0;
  float denominator = 0.0;
  for (int group = 0; group < region_layers; group++) {
    vec4 lit = texelFetch(shadow_data, ivec3(cell, group), 0);
    vec4 traced = texelFetch(shadow_data, ivec3(cell, region_layers + group), 0);
    for (int channel = 0; channel < 4; channel++) {
      int region = 4 * group + channel;
      if (region >= region_count) {
        break;
      }
      float cosine = dot(to_light, texelFetch(regions, ivec2(region, 0), 0).xyz);
      /* pow(0, k) is defined for k > 0, but pow of a negative number is not. */
      float weight = cosine > 0.0 ? pow(cosine, exponent) : 0.0;
      numerator += weight * lit[channel];
      denominator += weight * traced[channel];
    }
  }
  return denominator > 0.0 ? numerator / denominator : 0.0;
}

bool blocked(ivec2 cell, int point)
{
  vec4 masks = texelFetch(shadow_data, ivec3(cell, point / 64), 0);
  uint bits = uint(masks[(point % 64) / 16]);
  return ((bits >> uint(point % 16)) & 1u) != 0u;
}

void main()
{
  ivec2 cell = ivec2(gl_GlobalInvocationID.xy);
  int sample_index = cell.y * sample_width + cell.x;
  if (cell.x >= sample_width || sample_index >= sample_count) {
    return;
  }
  vec3 position = texelFetch(positions, cell, 0).xyz;
  vec3 normal = texelFetch(normals, cell, 0).xyz;
  vec3 geometric_normal = texelFetch(geometric, cell, 0).xyz;
  vec3 sum = vec3(0.0);
  for (int point = 0; point < point_count; point++) {
    vec4 place = texelFetch(lamps, ivec2(0, point), 0);
    vec3 scale = texelFetch(lamps, ivec2(1, point), 0).rgb;
    vec4 axis = texelFetch(lamps, ivec2(2, point), 0);
    int kind = int(place.w + 0.5);
    vec3 to_light;
    float factor;
    if (kind == KIND_SUN) {
      to_light = place.xyz;
      factor = max(dot(normal, to_light), 0.0);
    }
    else {
      vec3 offset = place.xyz - position;
      float light_distance = length(offset);
      float safe = max(light_distance, MIN_DISTANCE);
      to_light = offset / safe;
      float cos_receiver = max(dot(normal, to_light), 0.0);
      if (kind == KIND_AREA) {
        float cos_patch = max(-dot(to_light, axis.xyz), 0.0);
        factor = cos_receiver * cos_patch / (safe * safe);
      }
      else {
        factor = cos_receiver / (safe * safe);
        if (kind == KIND_SPOT) {
          factor *= spot_mask(-to_light, axis.xyz, axis.w, texelFetch(lamps, ivec2(3, point), 0).x);
        }
      }
      if (!(light_distance > MIN_DISTANCE)) {
        factor = 0.0;
      }
    }
    vec3 irradiance = factor * scale;
    bool above = dot(to_light, geometric_normal) > 0.0;
    if (!above || !any(greaterThan(irradiance, vec3(0.0)))) {
      continue; /* not lit: numpy neither traces nor looks up a fraction here */
    }
    float visibility = 1.0;
    if (shadow_mode == SHADOW_FRACTIONS) {
      visibility = fractions_visibility(cell, to_light);
    }
    else if (shadow_mode == SHADOW_EXACT && blocked(cell, point)) {
      visibility = 0.0;
    }
    sum += irradiance * visibility;
  }
  imageStore(accumulated, cell, vec4(sum, 0.0));
}
